"""Subregion compositing (eq. 6) and blending along subregion boundaries (eq. 7), in torch.

With per-subregion weights ``w_s(p)`` (from the eq. 7 weight map: ``r`` for the pixel's own
subregion ``i1``, ``1 - r`` for its neighbour ``i2``) and per-subregion convex-combination
coefficients ``c_{s,i}`` (eq. 2-5), the blended image in the standard geometry is

    I(p) = sum_s w_s(p) I^{R_s}(p) = sum_s w_s(p) sum_i c_{s,i} I_i(p).        (eq. 6 inside eq. 7)

Two ways to evaluate it, one function:

* sparse (default): for each subregion, only the pixels it touches (its own and its blending
  band) and only the examples with a coefficient above ``min_coeff`` (renormalised to sum to
  one), from per-subregion image stacks premultiplied by the weight map once when the model is
  prepared (see :class:`Compositor`);
* direct (the paper's implementation, the speed baseline): per pixel, the coefficient of every
  example (``r c_{i1} + (1 - r) c_{i2}``), then a weighted sum of every example image over every
  pixel.

With band-pass blending (Sec. 15 remedy, :mod:`stages.synthesis.bandpass`; ``detail_power`` p > 1)
each subregion's term becomes ``sum_i c_{s,i} I_i + sum_i (c^_{s,i} - c_{s,i}) D_i`` with the
examples' detail bands ``D_i`` and the sharpened weights ``c^ = c^p / sum c^p``.

Labels: ``0 .. S-1`` are the layout's subregions (face subregions composite the examples, the
teeth subregion the teeth examples, Sec. 8); label ``S`` is the outside of the face, always the
model's ``outside`` image (the neutral aligned to the standard geometry). Image stack order:
``M`` examples, ``Mt`` teeth examples, then the outside.

Teeth mixing. The teeth subregion is the inside of the inner lips; when the mouth is closed or
nearly so it is a sliver of a few pixels between the lips, where a real face shows lip (the
inner lip points of a closed mouth are rarely on one line), and the teeth examples, all with the
mouth open, squeezed into the sliver show a bright line of teeth along the lips. So with a
per-frame *teeth mix* ``m`` in [0, 1] (:func:`stages.synthesis.synthesize.teeth_mix`: 0 at the
neutral's opening, 1 from the least open teeth example's) the teeth subregion composites
``m sum_i c^teeth_i T_i + (1 - m) sum_i c^host_i I_i``: the teeth examples blended with the face
examples at the coefficients of the subregion holding the teeth (the lips), which at a closed
mouth show closed lips there. The teeth examples' own coefficients are sharpened first,
``c_i^p / sum_j c_j^p`` (``teeth_power`` p; :func:`stages.synthesis.bandpass.sharpened`): teeth are
rigid, each example has them at its own place relative to the lip points the alignment follows,
and an even blend of two shows both rows of teeth, doubled and blurred.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only; imported where used, so that importing this module stays light
    import torch

__all__ = ["Compositor", "Workspace", "prepare_compositor", "workspace", "mixed_coefficients", "composite", "MIN_COEFF"]

MIN_COEFF = 0.01  # coefficients skipped in compositing: the coherent weights spread over 4.5 examples a subregion; 0.01 keeps 3.8, drops 0.3 % of their mass


@dataclass
class _Segment:
    """One label's pixels in one role: the flat buffer slice it fills and its premultiplied images."""

    start: int
    stop: int
    stack: torch.Tensor  # (n_cand, 3, stop - start): candidate images at these pixels times the weight
    detail: torch.Tensor | None  # the same for the candidates' detail bands (band-pass blending), or None


@dataclass
class Compositor:
    """A synthesis model prepared for compositing on one device (see :func:`prepare_compositor`).

    Every pixel has one *primary* label (``i1``, weight ``r``) and, in a blending band, one
    *secondary* label (``i2``, weight ``1 - r``). Per frame each face label fills its slices of a
    primary and a secondary buffer (laid out label by label) with the weighted sum of its kept
    candidate images; the image is then two gathers, ``primary[:, primary_index] +
    secondary[:, secondary_index]`` (the secondary index of a pixel outside every band points at
    a zero column). The outside label's slices are constant and filled once; so is the image
    outside ``box``, the bounding box of the face labels' pixels (``background``), and the
    gathers run over the box only: the primary one over every box pixel (``box_primary_index``),
    the secondary one over the box's band pixels only (``box_band`` their positions in the box,
    ``box_band_secondary`` their columns), added where they belong.

    ``candidates[l]`` indexes the full image stack (``M`` examples, ``Mt`` teeth examples, the
    outside image; the teeth label's are the teeth examples, then the examples when it has a
    host for the teeth mix); ``alpha`` (H*W,) is the face alpha ``1 - w_S``; ``images`` (E, 3, H*W),
    ``r``, ``i1``, ``i2`` (H*W,) serve the direct path. With band-pass blending
    (``detail_power > 1``, :mod:`stages.synthesis.bandpass`) ``details`` (E, 3, H*W) holds the
    images' detail bands and every segment its premultiplied ``detail`` stack; otherwise None.
    """

    size: tuple[int, int]
    candidates: list[torch.Tensor]
    primary: list[_Segment]
    secondary: list[_Segment]
    primary_index: torch.Tensor
    secondary_index: torch.Tensor
    primary_template: torch.Tensor  # (3, H*W) with the outside label's slice filled
    secondary_template: torch.Tensor  # (3, n_band + 1)
    alpha: torch.Tensor
    images: torch.Tensor
    r: torch.Tensor
    i1: torch.Tensor
    i2: torch.Tensor
    details: torch.Tensor | None
    detail_power: float
    box: tuple[int, int, int, int]  # (y0, y1, x0, x1): bounding box of the pixels with a face label
    box_primary_index: torch.Tensor  # (h*w,) primary_index inside the box
    box_band: torch.Tensor  # (n,) positions (of the h*w) of the box pixels in a blending band
    box_band_secondary: torch.Tensor  # (n,) their secondary_index
    background: torch.Tensor  # (H*W, 4) channels-last: the composite outside the box (any coefficients), alpha
    teeth_label: int  # the teeth subregion, -1 if none
    teeth_host: int  # the subregion whose coefficients the teeth mix takes for the face examples, -1 if none
    teeth_power: float  # the teeth examples' coefficients are sharpened to this power (1: as solved)


@dataclass
class Workspace:
    """One thread's buffers for compositing frames one at a time (see :func:`workspace`).

    ``primary`` / ``secondary`` are private copies of the compositor's templates: the outside
    label's slices keep the standard image, the face labels' slices are rewritten whole for every
    frame. ``standard`` (1, 4, H, W) channels-last holds the last composited frame; outside
    ``Compositor.box`` it always holds ``Compositor.background``, which is therefore never copied
    again. ``face`` (3, h*w) and ``band`` (3, n) receive the gathers over the box and its band
    pixels. A workspace is not thread-safe: one per thread.
    """

    primary: torch.Tensor
    secondary: torch.Tensor
    standard: torch.Tensor
    face: torch.Tensor
    band: torch.Tensor


def prepare_compositor(
    model: dict[str, np.ndarray],
    *,
    device: str = "cpu",
    detail_power: float = 1.0,
    detail_sigma_px: float = 2.0,
    teeth_power: float = 1.0,
) -> Compositor:
    """Move a ``synthesis_model`` bundle's images and weight map to ``device`` in compositing form.

    Images become float32 sRGB in [0, 1]. ``detail_power`` > 1 turns on band-pass blending
    (:mod:`stages.synthesis.bandpass`): the detail band ``I - G_sigma * I`` (``sigma`` =
    ``detail_sigma_px``) is blended with the coefficients raised to that power and renormalised
    (``inf``: the dominant example's detail alone); 1 is plain eq. 6. ``teeth_power`` sharpens
    the teeth examples' coefficients the same way (module docstring, "Teeth mixing").
    """
    import torch
    from stages.synthesis.bandpass import detail_band

    if not detail_power >= 1:
        raise ValueError(f"detail_power must be >= 1, got {detail_power}")
    W, H = (int(v) for v in model["size"])
    teeth_flags = np.asarray(model["subregion_teeth"], bool)
    S = len(teeth_flags)
    M, Mt = len(model["examples"]), len(model["teeth"])
    stack = np.concatenate([model["examples"], model["teeth"], model["outside"][None]])
    images = torch.from_numpy(stack).to(device).reshape(len(stack), H * W, 3).permute(0, 2, 1).float().div(255.0).contiguous()
    details = None
    if detail_power > 1:
        details = detail_band(images.view(len(stack), 3, H, W), sigma_px=detail_sigma_px).reshape(len(stack), 3, H * W)
    r = torch.from_numpy(np.asarray(model["blend_r"], np.float32)).to(device).flatten()
    i1 = torch.from_numpy(np.asarray(model["blend_i1"], np.int64)).to(device).flatten()
    i2 = torch.from_numpy(np.asarray(model["blend_i2"], np.int64)).to(device).flatten()
    banded = i2 != i1
    primary_index = torch.empty(H * W, dtype=torch.long, device=device)
    secondary_index = torch.full((H * W,), int(banded.sum()), dtype=torch.long, device=device)
    candidates: list[torch.Tensor] = []
    primary: list[_Segment] = []
    secondary: list[_Segment] = []
    p_off = s_off = 0
    teeth_label = int(np.flatnonzero(teeth_flags)[0]) if teeth_flags.any() else -1
    host = int(model["teeth_host"]) if teeth_label >= 0 and "teeth_host" in model else -1
    for label in range(S + 1):
        if label == S:
            cand = torch.tensor([M + Mt], device=device)
        elif teeth_flags[label]:
            cand = torch.arange(M, M + Mt, device=device)
            if host >= 0:
                cand = torch.cat([cand, torch.arange(M, device=device)])
        else:
            cand = torch.arange(M, device=device)
        candidates.append(cand)
        pix = torch.nonzero(i1 == label).flatten()
        primary_index[pix] = torch.arange(p_off, p_off + len(pix), device=device)
        primary.append(
            _Segment(
                p_off,
                p_off + len(pix),
                _gather(images, cand, pix) * r[pix],
                None if details is None else _gather(details, cand, pix) * r[pix],
            )
        )
        p_off += len(pix)
        pix = torch.nonzero(banded & (i2 == label)).flatten()
        secondary_index[pix] = torch.arange(s_off, s_off + len(pix), device=device)
        secondary.append(
            _Segment(
                s_off,
                s_off + len(pix),
                _gather(images, cand, pix) * (1 - r[pix]),
                None if details is None else _gather(details, cand, pix) * (1 - r[pix]),
            )
        )
        s_off += len(pix)
    primary_template = torch.zeros(3, p_off, device=device)
    secondary_template = torch.zeros(3, s_off + 1, device=device)
    primary_template[:, primary[S].start : primary[S].stop] = primary[S].stack[0]
    secondary_template[:, secondary[S].start : secondary[S].stop] = secondary[S].stack[0]
    alpha = (
        1 - torch.where(i1 == S, r, torch.zeros_like(r)) - torch.where(banded & (i2 == S), 1 - r, torch.zeros_like(r))
    ).clamp(0, 1)
    face = ((i1 != S) | (banded & (i2 != S))).view(H, W)
    rows, cols = torch.nonzero(face.any(1)).flatten(), torch.nonzero(face.any(0)).flatten()
    box = (int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1) if len(rows) else (0, 0, 0, 0)
    y0, y1, x0, x1 = box
    background = torch.empty(H * W, 4, device=device)
    background[:, :3] = (
        primary_template.index_select(1, primary_index) + secondary_template.index_select(1, secondary_index)
    ).t()
    background[:, 3] = alpha
    box_secondary = secondary_index.view(H, W)[y0:y1, x0:x1].flatten()
    box_band = torch.nonzero(box_secondary != s_off).flatten()
    return Compositor(
        (W, H),
        candidates,
        primary,
        secondary,
        primary_index,
        secondary_index,
        primary_template,
        secondary_template,
        alpha,
        images,
        r,
        i1,
        i2,
        details,
        float(detail_power),
        box,
        primary_index.view(H, W)[y0:y1, x0:x1].flatten(),
        box_band,
        box_secondary[box_band],
        background,
        teeth_label,
        host,
        float(teeth_power),
    )


def workspace(comp: Compositor) -> Workspace:
    """Buffers for :func:`composite` of single frames (``workspace=``): the templates copied, a
    frame holding the background and the gathers' outputs, once instead of for every frame
    (5.8 + 7.7 + 2.6 MB at 600x800)."""
    import torch

    W, H = comp.size
    standard = comp.background.view(1, H, W, 4).clone().permute(0, 3, 1, 2)
    device = comp.background.device
    face = torch.empty(3, len(comp.box_primary_index), device=device)
    band = torch.empty(3, len(comp.box_band), device=device)
    return Workspace(comp.primary_template.clone(), comp.secondary_template.clone(), standard, face, band)


def _gather(stack: torch.Tensor, candidates: torch.Tensor, pixels: torch.Tensor) -> torch.Tensor:
    """``stack[candidates][:, :, pixels]`` for a ``(E, 3, H*W)`` stack, gathering the pixels first:
    ``stack[candidates]`` alone would copy every candidate image whole for each subregion."""
    return stack.index_select(2, pixels).index_select(0, candidates)


def _kept(c: list[float], min_coeff: float) -> list[tuple[int, float]]:
    """(index, weight) of the coefficients above ``min_coeff``, renormalised (the largest if none)."""
    keep = [(k, v) for k, v in enumerate(c) if v > min_coeff] or [max(enumerate(c), key=lambda kv: kv[1])]
    total = sum(v for _, v in keep)
    return [(k, v / total) for k, v in keep]


def _detail_terms(terms: list[tuple[int, float]], power: float) -> list[tuple[int, float]]:
    """(index, c^_k - c_k) of the kept terms: the detail-band correction of band-pass blending."""
    from stages.synthesis.bandpass import sharpened

    c = np.array([v for _, v in terms])
    return [(k, float(w - v)) for (k, v), w in zip(terms, sharpened(c, power=power)) if w != v]


def _fill(buffer: torch.Tensor, segment: _Segment, terms: list[tuple[int, float]], detail_terms: list[tuple[int, float]]) -> None:
    """``buffer[:, segment] = sum_k c_k stack_k + sum_k d_k detail_k`` without gathering the stacks."""
    import torch

    if segment.stop == segment.start:
        return
    view = buffer[:, segment.start : segment.stop]
    (k0, c0), rest = terms[0], terms[1:]
    torch.mul(segment.stack[k0], c0, out=view)
    for k, c in rest:
        view.add_(segment.stack[k], alpha=c)
    for k, d in detail_terms:
        view.add_(segment.detail[k], alpha=d)


def mixed_coefficients(comp: Compositor, coeffs: torch.Tensor, teeth_mix: np.ndarray | None) -> torch.Tensor:
    """The coefficients the compositor's candidates take: the teeth label's row becomes
    ``[m s(c^teeth), (1 - m) c^host]`` (the teeth mix, module docstring; ``m = 1`` when
    ``teeth_mix`` is None; ``s`` the sharpening to ``teeth_power``).

    Parameters
    ----------
    coeffs : (B, S, K) tensor, the QPs' coefficients
    teeth_mix : (B,) float in [0, 1], optional

    Returns
    -------
    (B, S, K') tensor, ``K' >= len(candidates[l])`` for every label (``coeffs`` itself when there
    is nothing to change: no teeth host and ``teeth_power`` 1).
    """
    import torch
    from stages.synthesis.bandpass import sharpened

    t, host = comp.teeth_label, comp.teeth_host
    if t < 0 or (host < 0 and comp.teeth_power == 1):
        return coeffs
    M = len(comp.candidates[host]) if host >= 0 else 0
    Mt = len(comp.candidates[t]) - M
    B, S, K = coeffs.shape
    out = torch.zeros(B, S, max(K, len(comp.candidates[t])), dtype=coeffs.dtype, device=coeffs.device)
    out[..., :K] = coeffs
    teeth = coeffs[:, t, :Mt]
    if comp.teeth_power != 1:
        teeth = torch.as_tensor(
            sharpened(teeth.detach().cpu().numpy().clip(0, None), power=comp.teeth_power),
            dtype=coeffs.dtype,
            device=coeffs.device,
        )
    m = (
        torch.ones(B, dtype=coeffs.dtype, device=coeffs.device)
        if teeth_mix is None or host < 0
        else torch.as_tensor(np.asarray(teeth_mix, np.float64), dtype=coeffs.dtype, device=coeffs.device)
    )
    out[:, t, :Mt] = m[:, None] * teeth
    if host >= 0:
        out[:, t, Mt : Mt + M] = (1 - m)[:, None] * coeffs[:, host, :M]
    out[:, t, Mt + M :] = 0
    return out


def composite(
    comp: Compositor,
    coeffs: torch.Tensor,
    *,
    min_coeff: float = MIN_COEFF,
    direct: bool = False,
    workspace: Workspace | None = None,
    teeth_mix: np.ndarray | None = None,
) -> torch.Tensor:
    """Blend the aligned example images by per-subregion coefficients (eq. 6, 7).

    Parameters
    ----------
    comp : Compositor
    coeffs : (B, S, K) tensor
        Per frame and subregion, the convex-combination coefficients: over the ``M`` examples for
        face subregions, over the ``Mt`` teeth examples (first ``Mt`` entries) for the teeth
        subregion; ``K >= max(M, Mt)``, extra entries ignored.
    min_coeff : float
        Sparse path only: coefficients at or below it are skipped and the rest renormalised.
    direct : bool
        Composite every example at every pixel (the paper's implementation) instead.
    workspace : Workspace, optional
        Sparse path, one frame (``B = 1``): composite in these buffers (:func:`workspace`) and
        return ``workspace.standard``, which the next call with the same workspace overwrites.
    teeth_mix : (B,) float in [0, 1], optional
        The teeth mix of each frame (module docstring; :func:`mixed_coefficients`); None: the
        teeth examples alone.

    The compositor's ``detail_power`` (:func:`prepare_compositor`) adds the band-pass detail
    term in both paths (see the module docstring).

    Returns
    -------
    (B, 4, H, W) float32: sRGB colour in [0, 1] in the standard geometry, and the face alpha; in
    channels-last memory (``permute(0, 2, 3, 1)`` of it is contiguous), the layout the CPU warp
    (:func:`stages.synthesis.warp.warp_images`, ``cv2.remap``) reads without a copy.
    """
    import torch

    W, H = comp.size
    B, S = coeffs.shape[:2]
    coeffs = mixed_coefficients(comp, coeffs, teeth_mix)
    device = comp.images.device
    if workspace is not None and (direct or B != 1):
        raise ValueError(f"a workspace composites one frame on the sparse path, got B={B}, direct={direct}")
    if workspace is not None:
        out = workspace.standard.view(1, 4, H * W)  # (1, 4, H*W) view, channels-last
    else:
        out = torch.empty(B, H * W, 4, device=device).permute(0, 2, 1)  # (B, 4, H*W) view, channels-last
    if direct:
        out[:, 3] = comp.alpha
        full = torch.zeros(B, S + 1, comp.images.shape[0], device=device)
        for label in range(S):
            cand = comp.candidates[label]
            full[:, label, cand] = coeffs[:, label, : len(cand)].to(device=device, dtype=torch.float32)
        full[:, S, -1] = 1.0
        if comp.details is not None:
            from stages.synthesis.bandpass import sharpened

            sharp = torch.zeros_like(full)
            for label in range(S + 1):
                cand = comp.candidates[label]
                c = full[:, label, cand].double().cpu().numpy()
                sharp[:, label, cand] = torch.from_numpy(sharpened(c, power=comp.detail_power)).to(full)
        for b in range(B):
            per_pixel = comp.r[:, None] * full[b, comp.i1] + (1 - comp.r)[:, None] * full[b, comp.i2]  # (H*W, E)
            out[b, :3] = torch.einsum("pe,ecp->cp", per_pixel, comp.images)
            if comp.details is not None:
                per_pixel = comp.r[:, None] * sharp[b, comp.i1] + (1 - comp.r)[:, None] * sharp[b, comp.i2] - per_pixel
                out[b, :3] += torch.einsum("pe,ecp->cp", per_pixel, comp.details)
    else:
        table = coeffs.detach().to("cpu", torch.float64).tolist()
        if workspace is None:
            primary, secondary = comp.primary_template.clone(), comp.secondary_template.clone()
        else:
            primary, secondary = workspace.primary, workspace.secondary
        for b in range(B):
            for label in range(S):
                terms = _kept(table[b][label][: len(comp.candidates[label])], min_coeff)
                detail = [] if comp.details is None else _detail_terms(terms, comp.detail_power)
                _fill(primary, comp.primary[label], terms, detail)
                _fill(secondary, comp.secondary[label], terms, detail)
            y0, y1, x0, x1 = comp.box
            frame = out[b].t()  # (H*W, 4), contiguous
            if workspace is None:
                frame.copy_(comp.background)
            inside = frame.view(H, W, 4)[y0:y1, x0:x1, :3].permute(2, 0, 1)  # (3, h, w) view
            face = torch.index_select(
                primary, 1, comp.box_primary_index, out=None if workspace is None else workspace.face
            )  # (3, h*w)
            band = torch.index_select(secondary, 1, comp.box_band_secondary, out=None if workspace is None else workspace.band)
            face.index_add_(1, comp.box_band, band)
            inside.copy_(face.view(inside.shape))
    return out.view(B, 4, H, W)
