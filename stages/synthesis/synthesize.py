"""Runtime expression synthesis (Sec. 6-8, 11): target geometry per frame -> expression images.

Per chunk of frames: the batched convex-hull QP (eq. 2-5) for every frame and subregion, made
coherent in time by a joint bilateral filter over the frames around (:mod:`stages.synthesis.coherence`:
no texture pops while a subregion holds still, no lag while it moves), the
compositing and boundary blending of the aligned examples (eq. 6, 7; teeth from the teeth
examples, Sec. 8) in the standard geometry, then the triangulation-based warp of the whole image
from the standard geometry to the frame's geometry (Sec. 7, last paragraph).

Modes
-----
``full``       the method of the paper (per-subregion convex combinations);
``global``     one convex combination over the whole face (Pighin et al.; teeth still separate);
``warp-only``  traditional expression mapping: the neutral image warped to the frame's geometry,
               no expression details.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np

from runner.stage import Context, FrameStage, Param, StageError, StreamInfo
from stages.geometry.bundles import DISPLACEMENTS, POINTS, SIMILARITY
from stages.render3d.bundles import HEAD3D
from stages.synthesis.bundles import SYNTHESIS_COEFFS, SYNTHESIS_MODEL
from stages.geometry.mapping import rms_radius
from stages.synthesis.coherence import coherent_coefficients
from stages.synthesis.composite import MIN_COEFF, Compositor, Workspace, composite, prepare_compositor, workspace
from stages.synthesis.coefficients import SubregionQP, target_geometry
from stages.synthesis.warp import Buffers, scratch, warp_images

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only; imported where used, so that importing this module stays light
    import torch

__all__ = [
    "MODES",
    "HEAD_MOTION",
    "HeadTurn",
    "Synthesizer",
    "half_float_planes",
    "head_motion_points",
    "head_motion_frame",
    "teeth_mix",
    "output_size",
    "Synthesize",
]

MODES = ("full", "warp-only", "global")
HEAD_MOTION = ("auto", "depth", "similarity", "none")
DETAIL_POWER = 1.0  # band-pass blending defaults (docs/synthesis.md, "Fine texture")
DETAIL_SIGMA_PX = 2.0
TEETH_POWER = 4.0  # teeth examples' coefficients sharpened (composite.py, "Teeth mixing"): (0.6, 0.4) -> (0.84, 0.16)
RIDGE_PX = 0.0  # coefficient regularisation of the QPs (docs/synthesis.md, "Per-subregion vs global on real faces")
COHERENCE_FRAMES = 2.0  # example weights coherent in time (stages.synthesis.coherence)
COHERENCE_SIZE = 0.035
MEMO_FRAMES = 2048  # frames whose QP coefficients a Synthesizer keeps (about 4 KB each)
# Output size and memory (docs/synthesis.md, "Output size"): a run's peak memory grows with the
# output's pixels (the synthesized chunks, and the writers and previews reading them). Measured
# with /usr/bin/time on the bundled pipeline (fixtures/clips/calm.mp4, 2 cores, chunk_frames
# 16): 2.03 GB at 960x1280, 3.86 GB at 1440x1920.
GB_PER_OUTPUT_MEGAPIXEL = 1.2
RUN_BASE_GB = 0.6
RUN_BUDGET_GB = 8.0  # the estimated peak memory an output size may take
MAX_OUTPUT_PIXELS = int((RUN_BUDGET_GB - RUN_BASE_GB) / GB_PER_OUTPUT_MEGAPIXEL * 1e6)  # 6.2 MP: 2160x2880, 3200x1800
MAX_OUTPUT_WIDTH = 3840  # px, whatever the pack's aspect ratio


def head_motion_points(
    points: np.ndarray, params: np.ndarray, *, source_center: np.ndarray, target_center: np.ndarray, scale: float
) -> np.ndarray:
    """Carry the performer's 2D head motion (eq. 8 similarity) onto target points.

    The performer's similarity ``x -> A x + t`` (``A = [[a, -b], [b, a]]``, neutral -> frame)
    is split into its rotation/scale ``A`` about the performer's face centre ``source_center``
    and the displacement of that centre ``delta = A c_s + t - c_s``. On the target, ``A`` turns
    and scales about ``target_center`` and the centre moves by ``scale * delta``
    (``scale`` = target face size / performer face size).

    Parameters
    ----------
    points : (B, P, 2) float, px
    params : (B, 4) float, (a, b, tx, ty) per frame
    source_center, target_center : (2,) float, px
    scale : float

    Returns
    -------
    (B, P, 2) float64, px.
    """
    a, b, tx, ty = (params[:, k] for k in range(4))
    A = np.stack([np.stack([a, -b], -1), np.stack([b, a], -1)], -2)  # (B, 2, 2)
    delta = np.einsum("bij,j->bi", A, source_center) + np.stack([tx, ty], -1) - source_center
    rel = np.asarray(points, np.float64) - target_center
    return np.einsum("bij,bpj->bpi", A, rel) + target_center + scale * delta[:, None, :]


def head_motion_frame(
    performer_neutral: np.ndarray, performer_names: np.ndarray, target_neutral: np.ndarray, target_names: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """Face centres and size ratio for :func:`head_motion_points`, from the points both faces share.

    Parameters
    ----------
    performer_neutral : (n, 2) float, px, the performer's neutral tracked points
    performer_names : (n,) str
    target_neutral : (N, 2) float, px, the target's neutral feature points
    target_names : (N,) str

    Returns
    -------
    source_center, target_center : (2,) float, px
        Centroids of the shared points on each neutral.
    scale : float
        Target / performer face size: the ratio of the RMS distances of the shared points to
        their centroid.
    """
    where = {str(n): k for k, n in enumerate(target_names)}
    shared = [(k, where[str(n)]) for k, n in enumerate(performer_names) if str(n) in where]
    if len(shared) < 2:
        raise StageError("synthesis.synthesize: input 'performer': fewer than 2 of its points are in the target's layout")
    src = np.asarray(performer_neutral, np.float64)[[k for k, _ in shared]]
    dst = np.asarray(target_neutral, np.float64)[[j for _, j in shared]]
    c_s, c_t = src.mean(0), dst.mean(0)
    size_s = np.sqrt(((src - c_s) ** 2).sum(1).mean())
    size_t = np.sqrt(((dst - c_t) ** 2).sum(1).mean())
    if size_s <= 0:
        raise StageError("synthesis.synthesize: input 'performer': the neutral points all coincide")
    return c_s, c_t, float(size_t / size_s)


def half_float_planes(
    rgba: torch.Tensor, *, out: tuple[np.ndarray, np.ndarray] | None = None, buffers: Buffers | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Colour and alpha planes as contiguous half floats, the ``frames`` / ``mask`` outputs.

    Parameters
    ----------
    rgba : (B, 4, H, W) float tensor, any device and memory layout
    out : (frames, mask), optional
        C-contiguous float16 arrays of the shapes below to write into (e.g. rows of a chunk's
        output arrays) instead of new ones.
    buffers : Buffers, optional
        This thread's :class:`~stages.synthesis.warp.Buffers` for the CPU path's one-frame
        half-float temporary.

    Returns
    -------
    frames : (B, H, W, 3) float16 ndarray
    mask : (B, H, W, 1) float16 ndarray

    On the CPU each frame is converted whole (RGBA float32 -> float16, contiguous to contiguous,
    torch's conversion) and then split on the half floats' 16-bit patterns: colour by
    ``cv2.cvtColor`` (``BGRA2BGR`` drops the fourth channel, vectorised), alpha by a strided
    ``np.copyto``. Both are vectorised copies; ``cv2.mixChannels`` loops per element, and splitting
    the float32 channels before converting converts each part separately, both several times slower.
    """
    import cv2
    import torch

    hwc = rgba.detach().permute(0, 2, 3, 1)
    if rgba.device.type != "cpu":
        frames, mask = hwc[..., :3].to(torch.float16).cpu().numpy(), hwc[..., 3:].to(torch.float16).cpu().numpy()
        if out is None:
            return frames, mask
        out[0][...], out[1][...] = frames, mask
        return out
    if rgba.dtype != torch.float32 or rgba.shape[1] != 4:
        raise ValueError(f"rgba must be (B, 4, H, W) float32, got {tuple(rgba.shape)} {rgba.dtype}")
    B, H, W, _ = hwc.shape
    if out is None:
        out = np.empty((B, H, W, 3), np.float16), np.empty((B, H, W, 1), np.float16)
    for array, C in zip(out, (3, 1)):
        if array.shape != (B, H, W, C) or array.dtype != np.float16 or not array.flags.c_contiguous:
            raise ValueError(f"out arrays must be C-contiguous float16 ({B}, {H}, {W}, {C}), got {array.shape} {array.dtype}")
    half = scratch(buffers, "half", (H, W, 4), torch.float16)
    bits = half.numpy().view(np.uint16)
    for b in range(B):
        half.copy_(hwc[b])
        cv2.cvtColor(bits, cv2.COLOR_BGRA2BGR, dst=out[0][b].view(np.uint16))
        np.copyto(out[1][b].view(np.uint16), bits[..., 3:])
    return out


def teeth_mix(points: np.ndarray, polygon: np.ndarray, open_area: np.ndarray) -> np.ndarray:
    """The teeth mix of each frame (:mod:`stages.synthesis.composite`, "Teeth mixing").

    ``m = smoothstep(a0, a1, a)`` of the teeth polygon's area ``a`` in the frame, with ``a0`` its
    area at the neutral (what a closed mouth looks like in this pack: the inner lip points are
    rarely on one line) and ``a1`` at the least open teeth example (where teeth show whole).

    Parameters
    ----------
    points : (B, N, 2) float, px
    polygon : (n,) int, the teeth subregion's outline
    open_area : (2,) float, ``(a0, a1)`` px^2 (the model's ``teeth_open_area``)

    Returns
    -------
    (B,) float64 in [0, 1]; ones when ``a1 <= a0`` (no closed state to mix in) or no polygon.
    """
    from stages.synthesis.build import polygon_area

    B = len(points)
    a0, a1 = (float(v) for v in open_area)
    if len(polygon) < 3 or a1 <= a0:
        return np.ones(B)
    u = np.clip((polygon_area(np.asarray(points, np.float64)[:, polygon]) - a0) / (a1 - a0), 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def output_points(points: np.ndarray, size: tuple[int, int], out_size: tuple[int, int]) -> np.ndarray:
    """Positions ``(..., 2)`` px in an image of ``size (W, H)`` -> in one of ``out_size`` (pixel centres at integers)."""
    if tuple(size) == tuple(out_size):
        return np.asarray(points, np.float64)
    scale = np.asarray(out_size, np.float64) / np.asarray(size, np.float64)
    return (np.asarray(points, np.float64) + 0.5) * scale - 0.5


class Synthesizer:
    """A synthesis model prepared on a device; :meth:`render` maps geometry to images.

    Parameters
    ----------
    model : dict of arrays
        A ``synthesis_model`` bundle (see :mod:`stages.synthesis.build`).
    device : str
    detail_power, detail_sigma_px : float
        Band-pass blending (Sec. 15 remedy, :mod:`stages.synthesis.bandpass`): the examples'
        detail bands (finer than a Gaussian of ``detail_sigma_px``) are blended with the
        coefficients raised to ``detail_power`` and renormalised; 1 is plain eq. 6.
    ridge_px : float
        Coefficient regularisation ``tau`` of the QPs, px (:class:`SubregionQP`; 0: plain eq. 2).
    teeth_power : float
        The teeth examples' coefficients sharpened to this power (:mod:`stages.synthesis.composite`,
        "Teeth mixing"; 1: as the QP solved them).
    memo_frames : int
        How many frames' QP coefficients :meth:`coefficients` keeps (0: none, every QP solved).
    output_size : (W, H), optional
        The output images' size (the same aspect ratio as the pack's, up to a pixel's rounding);
        the pack's when omitted. Geometry stays in pack px; it is scaled to the output.
    padding_mode : ``"border" | "zeros"``
        The colour the warp reads beyond the source image before the fill: its edge repeated
        (``border``, what a pixel on the edge of the validity matte keeps a share of) or 0.
    """

    def __init__(
        self,
        model: Mapping[str, np.ndarray],
        *,
        device: str = "cpu",
        detail_power: float = DETAIL_POWER,
        detail_sigma_px: float = DETAIL_SIGMA_PX,
        ridge_px: float = RIDGE_PX,
        teeth_power: float = TEETH_POWER,
        memo_frames: int = MEMO_FRAMES,
        output_size: tuple[int, int] | None = None,
        padding_mode: str = "border",
    ) -> None:
        import torch

        self.device = device
        self.qp = SubregionQP(model, device=device, ridge_px=ridge_px)
        self.compositor: Compositor = prepare_compositor(
            dict(model), device=device, detail_power=detail_power, detail_sigma_px=detail_sigma_px, teeth_power=teeth_power
        )
        self.size = tuple(int(v) for v in model["size"])
        self.out_size = self.size if output_size is None else tuple(int(v) for v in output_size)
        self.padding_mode = padding_mode
        self.anchors = np.asarray(model["anchors"], np.float64)
        self.anchor_kind = np.asarray(model["anchor_kind"])
        self.anchor_hull = np.asarray(model["anchor_hull"], np.int64)
        self.face_outline = np.asarray(model["face_outline"], np.int64)
        self.triangles = np.asarray(model["triangles"])
        self.mouth_triangles = np.asarray(model["mouth_triangles"], bool)
        self.surround_triangles = (self.triangles >= len(model["standard_points"])).any(axis=1)  # an anchor corner
        self.teeth_polygon = np.asarray(model["teeth_polygon"], np.int64)
        self.teeth_open_area = np.asarray(model["teeth_open_area"], np.float64)
        self.standard_np = np.asarray(model["standard_points"], np.float64)
        self.standard_points = torch.from_numpy(np.concatenate([self.standard_np, self.anchors])).to(device)
        self.neutral_points = torch.from_numpy(np.concatenate([model["neutral_points"], self.anchors])).to(device)
        self.neutral_rgba = self._neutral_rgba(model)
        self.mattes, self.neutral_mattes = self._mattes(model)
        self.center = np.asarray(model["neutral_points"], np.float64).mean(0)
        self._local = threading.local()  # per thread: the compositing workspace, the warp's buffers
        self._memo: OrderedDict[tuple[str, bytes], torch.Tensor] = OrderedDict()  # (mode, points bytes) -> (S, K)
        self._memo_lock = threading.Lock()
        self.memo_frames = int(memo_frames)

    def _neutral_rgba(self, model: Mapping[str, np.ndarray]) -> torch.Tensor:
        """The neutral image with the face alpha carried into its geometry, the ``warp-only`` source.

        The face alpha ``1 - w_S`` (eq. 7's weight of the outside) lives in the standard geometry;
        it is warped once, here, from the standard points to the neutral points (same
        triangulation, anchors fixed), so that a ``warp-only`` frame is one warp of a 4-channel
        image like the other modes' composite. The composition of the two piecewise-affine maps
        is the map standard -> frame, so only the resampling differs: the alpha is interpolated
        twice. It is linear across the blending bands, where bilinear interpolation is exact, so
        it changes at the face's edge only: at the ends of the ramps and, most, at eq. 7's triple
        junctions, where it steps within a pixel (figures in docs/synthesis.md, ``warp-only``).

        Returns
        -------
        (1, 4, H, W) float32 tensor on the device: sRGB colour (8-bit values / 255) and face alpha
        in [0, 1]; channels-last memory (``permute(0, 2, 3, 1)`` of it is contiguous).
        """
        import torch

        W, H = self.size
        alpha = self.compositor.alpha.view(1, 1, H, W)
        alpha = warp_images(alpha, self.standard_points[None], self.neutral_points[None], self.triangles).clamp_(0, 1)
        rgba = torch.empty(1, H, W, 4, dtype=torch.float32, device=self.device)
        rgba[..., :3] = torch.from_numpy(np.asarray(model["neutral"])).to(self.device).float() / 255.0
        rgba[..., 3] = alpha[:, 0]
        return rgba.permute(0, 3, 1, 2)

    def _mattes(self, model: Mapping[str, np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
        """The static planes warped with each frame: validity and head matte, ``(1, 2, H, W)``
        float32 channels-last, in the standard geometry (the composite's) and in the neutral's
        (``warp-only``: the neutral's own matte, the head matte carried as the face alpha is)."""
        import torch

        W, H = self.size
        head = torch.from_numpy(np.asarray(model["head_matte"], np.float32)).to(self.device)
        standard = torch.empty(1, H, W, 2, dtype=torch.float32, device=self.device)
        standard[..., 0] = torch.from_numpy(np.asarray(model["valid"], np.float32)).to(self.device)
        standard[..., 1] = head
        neutral = torch.empty(1, H, W, 2, dtype=torch.float32, device=self.device)
        neutral[..., 0] = torch.from_numpy(np.asarray(model["neutral_valid"], np.float32)).to(self.device)
        neutral[..., 1] = warp_images(
            head.view(1, 1, H, W), self.standard_points[None], self.neutral_points[None], self.triangles
        )[:, 0].clamp_(0, 1)
        return standard.permute(0, 3, 1, 2), neutral.permute(0, 3, 1, 2)

    def _workspace(self) -> Workspace:
        """This thread's compositing buffers (:func:`stages.synthesis.composite.workspace`)."""
        if getattr(self._local, "workspace", None) is None:
            self._local.workspace = workspace(self.compositor)
        return self._local.workspace

    def _buffers(self) -> Buffers:
        """This thread's warp and half-float buffers (:class:`stages.synthesis.warp.Buffers`)."""
        if getattr(self._local, "buffers", None) is None:
            self._local.buffers = Buffers()
        return self._local.buffers

    def coefficients(self, points: np.ndarray, *, mode: str = "full") -> torch.Tensor:
        """The QPs' coefficients (eq. 2-5) of a chunk, as :meth:`SubregionQP.coefficients`, with a memo.

        A frame's coefficients depend only on its points and the mode, and its QP gives bit for
        bit the same result alone as in a batch; so the coefficients of the last ``memo_frames``
        frames are kept and a frame synthesized again (the runner recomputes single frames for a
        reader that asks after the chunk was dropped) skips its QP, which alone costs about half
        a 16-frame batch (the interior-point iterations are dominated by per-operation overhead).

        Parameters
        ----------
        points : (B, N, 2) float, px
        mode : ``"full" | "warp-only" | "global"``

        Returns
        -------
        (B, S, K) float64 tensor on the synthesizer's device; zeros in ``warp-only`` mode (no QP).
        """
        import torch

        points = np.ascontiguousarray(points, np.float64)
        if mode == "warp-only":
            return torch.zeros(len(points), self.qp.n_subregions, self.qp.K, dtype=torch.float64, device=self.device)
        keys = [(mode, frame.tobytes()) for frame in points]
        with self._memo_lock:
            rows = [self._memo.get(key) for key in keys]
        missing = [i for i, row in enumerate(rows) if row is None]
        if missing:
            solved, _ = self.qp.coefficients(points[missing], mode=mode)
            with self._memo_lock:
                for i, row in zip(missing, solved):
                    rows[i] = self._memo[keys[i]] = row
                while len(self._memo) > self.memo_frames:
                    self._memo.popitem(last=False)
        return torch.stack(rows)

    def teeth_mix(self, points: np.ndarray) -> np.ndarray:
        """``(B,)``: :func:`teeth_mix` of the frames' points ``(B, N, 2)``."""
        return teeth_mix(points, self.teeth_polygon, self.teeth_open_area)

    def render(self, points: np.ndarray, **options: Any) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Synthesize the expression images of a chunk of frames (see :meth:`render_rgba`).

        Returns
        -------
        rgb : (B, 3, H, W) float32 sRGB in [0, 1]
        alpha : (B, 1, H, W) float32 face alpha in [0, 1]
        coeffs : (B, S, K) float64 (zeros in ``warp-only`` mode)
        """
        rgba, _, coeffs = self.render_rgba(points, **options)
        return rgba[:, :3], rgba[:, 3:], coeffs

    def render_half(
        self,
        points: np.ndarray,
        *,
        mode: str = "full",
        similarity: np.ndarray | None = None,
        turn: HeadTurn | None = None,
        direct: bool = False,
        coeffs: torch.Tensor | None = None,
        progress: Callable[[int], None] = lambda n: None,
        **options: Any,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, torch.Tensor]:
        """Synthesize a chunk as the stage outputs it: the QPs batched, then frame by frame into half floats.

        Frame by frame because a chunk's (B, 4, H, W) float32 buffers (123 MB for 16 frames at
        600x800) exceed glibc's largest mmap threshold and were mapped fresh, and faulted in
        page by page, every chunk; one frame composites in this thread's workspace and is warped
        and converted in this thread's buffers.

        Parameters
        ----------
        points, mode, similarity, turn, direct
            As :meth:`render_rgba`; ``similarity`` (B, 4) and ``turn`` are sliced per frame.
        coeffs : (B, S, K) tensor, optional
            Composite with these coefficients (e.g. :func:`stages.synthesis.coherence.coherent_coefficients`)
            instead of each frame's own QP solution.
        progress : callable
            Called with 1 after each frame.
        **options
            The other keywords of :meth:`render_rgba` (``source_center``, ``target_center``,
            ``motion_scale``, ``min_coeff``), the same for every frame.

        Returns
        -------
        frames : (B, H, W, 3) float16, sRGB in [0, 1], the whole frame (filled where no source
            pixel is: see ``filled``)
        mask : (B, H, W, 1) float16, face alpha
        head : (B, H, W, 1) float16, head matte
        filled : (B, H, W, 1) float16, how much of each pixel is filled (1 - validity)
        coeffs : (B, S, K) float64 tensor (zeros in ``warp-only`` mode)
        """
        points = np.asarray(points, np.float64)
        if coeffs is None:
            coeffs = self.coefficients(points, mode=mode)  # the QPs batched
        W, H = self.out_size
        B = len(points)
        frames = np.empty((B, H, W, 3), np.float16)
        mask = np.empty((B, H, W, 1), np.float16)
        head = np.empty((B, H, W, 1), np.float16)
        filled = np.empty((B, H, W, 1), np.float16)
        buffers = self._buffers()
        for i in range(B):
            one = slice(i, i + 1)
            rgba, mattes, _ = self.render_rgba(
                points[one],
                mode=mode,
                similarity=None if similarity is None else similarity[one],
                turn=None if turn is None else turn.frames(one),
                direct=direct,
                coeffs=coeffs[one],
                buffers=buffers,
                **options,
            )
            half_float_planes(rgba, out=(frames[one], mask[one]), buffers=buffers)
            matte_planes(mattes[0], head=head[i, ..., 0], filled=filled[i, ..., 0])
            progress(1)
        return frames, mask, head, filled, coeffs

    def _destinations(
        self,
        points: np.ndarray,
        similarity: np.ndarray | None,
        turn: HeadTurn | None,
        *,
        source_center: np.ndarray | None,
        target_center: np.ndarray | None,
        motion_scale: float,
    ) -> tuple[np.ndarray, list[np.ndarray]]:
        """Per frame the warp's destination points (feature points and anchors, output px) and the
        triangles in painting order: the head turned in depth (:mod:`stages.synthesis.turn`), the
        2D similarity (eq. 8-9, :func:`head_motion_points`) or neither."""
        B = len(points)
        vertices = np.concatenate([points, np.broadcast_to(self.anchors, (B,) + self.anchors.shape)], 1)
        if turn is not None:
            from stages.mesh3d.model import lift
            from stages.render3d.frame import scaled_intrinsics
            from stages.synthesis.surround import anchor_depth, motion_weights
            from stages.synthesis.turn import depth_order, turned_points

            lifted = lift(self.standard_np, turn.depth, turn.camera)
            depth = np.concatenate(
                [
                    turn.depth,
                    anchor_depth(lifted, self.standard_np, self.anchors, self.anchor_kind, self.anchor_hull, self.face_outline),
                ]
            )
            weight = np.concatenate([np.ones(len(turn.depth)), motion_weights(self.anchor_kind)])
            A_out = scaled_intrinsics(turn.camera, self.out_size[0] / self.size[0])
            dst, z = turned_points(vertices, depth, weight, turn.camera, turn.R, turn.t, A_out=A_out)
            order = [
                depth_order(self.triangles, z[b], behind=self.mouth_triangles, under=self.surround_triangles) for b in range(B)
            ]
            return dst, order
        if similarity is not None:
            c_t = self.center if target_center is None else np.asarray(target_center, np.float64)
            c_s = c_t if source_center is None else np.asarray(source_center, np.float64)
            vertices = head_motion_points(
                vertices, np.asarray(similarity, np.float64), source_center=c_s, target_center=c_t, scale=motion_scale
            )
        return output_points(vertices, self.size, self.out_size), [self.triangles] * B

    def render_rgba(
        self,
        points: np.ndarray,
        *,
        mode: str = "full",
        similarity: np.ndarray | None = None,
        turn: HeadTurn | None = None,
        source_center: np.ndarray | None = None,
        target_center: np.ndarray | None = None,
        motion_scale: float = 1.0,
        min_coeff: float = MIN_COEFF,
        direct: bool = False,
        coeffs: torch.Tensor | None = None,
        buffers: Buffers | None = None,
        fill: bool = True,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Synthesize the expression images of a chunk of frames, colour and alpha in one tensor.

        Parameters
        ----------
        points : (B, N, 2) float, px
            The target's feature points per frame (all N, from motion propagation), pack px.
        mode : ``"full" | "warp-only" | "global"``
        similarity : (B, 4) float, optional
            The performer's head motion (a, b, tx, ty) per frame, carried onto the output as a 2D
            similarity (:func:`head_motion_points`); ``source_center`` / ``target_center`` are the
            performer's / target's face centres (both default to the centroid of the target's
            neutral points), ``motion_scale`` target / performer face size.
        turn : HeadTurn, optional
            The head's rigid motion in 3D and the target's depths: the depth-aware warp of the
            whole image (:mod:`stages.synthesis.turn`); takes precedence over ``similarity``.
        min_coeff : float
            Coefficients skipped in compositing (see :func:`composite`).
        direct : bool
            Composite every example at every pixel (the paper's implementation; speed baseline).
        coeffs : (B, S, K) tensor, optional
            Composite with these coefficients instead of solving the QPs (``full`` / ``global``
            modes; e.g. :func:`lab.synthesis.oracle.texture_oracle`); ``warp-only`` mode
            composites nothing and returns them as given.
        buffers : Buffers, optional
            Warp in these buffers (:func:`stages.synthesis.warp.warp_images`); ``rgba`` and the
            mattes are then overwritten by the next call with the same buffers.
        fill : bool
            Fill the pixels no real source pixel covers (:func:`stages.fill.fill_invalid`);
            False leaves them black (the mattes are the same).

        Returns
        -------
        rgba : (B, 4, H, W) float32
            sRGB colour and face alpha, in [0, 1], at the output size; on the CPU in channels-last
            memory (``permute(0, 2, 3, 1)`` of it is contiguous).
        mattes : (B, 2, H, W) float32
            The validity (1: every source pixel behind it is real; positions beyond the source
            image or its matte read 0) and the head matte, warped as the image is.
        coeffs : (B, S, K) float64 (zeros in ``warp-only`` mode unless given)

        Every mode is one warp of a 4-channel image to the frame's geometry: ``full`` / ``global``
        the composite in the standard geometry (eq. 6, 7) from the standard points, ``warp-only``
        the neutral image with the face alpha in its geometry (:meth:`_neutral_rgba`) from the
        neutral points. Pixels the mattes say no real source pixel covers are filled (``fill``);
        their colour before the fill is what ``padding_mode`` reads beyond the source, which only
        the fill's weight ``validity`` of a pixel on the edge of the matte keeps.
        """
        import torch

        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        points = np.asarray(points, np.float64)
        B = len(points)
        dst, triangles = self._destinations(
            points, similarity, turn, source_center=source_center, target_center=target_center, motion_scale=motion_scale
        )
        dst_t = torch.from_numpy(dst).to(self.device)
        if coeffs is None:
            coeffs = self.coefficients(points, mode=mode)
        elif tuple(coeffs.shape) != (B, self.qp.n_subregions, self.qp.K):
            raise ValueError(f"coeffs must be (B, S, K) = ({B}, {self.qp.n_subregions}, {self.qp.K}), got {tuple(coeffs.shape)}")
        if mode == "warp-only":
            source, source_points, mattes = self.neutral_rgba, self.neutral_points, self.neutral_mattes
        else:
            one = B == 1 and not direct  # one frame: in this thread's workspace (no per-frame buffers)
            source = composite(
                self.compositor,
                coeffs,
                min_coeff=min_coeff,
                direct=direct,
                workspace=self._workspace() if one else None,
                teeth_mix=self.teeth_mix(points),
            )
            source_points, mattes = self.standard_points, self.mattes
        if B == 1:
            out, warped = warp_images(
                source,
                source_points[None],
                dst_t,
                triangles[0],
                size=self.out_size,
                padding_mode=self.padding_mode,
                buffers=buffers,
                extra=mattes,
            )
        else:  # frame by frame: each has its own triangle order
            pairs = [
                warp_images(
                    source[b : b + 1] if len(source) > 1 else source,
                    source_points[None],
                    dst_t[b : b + 1],
                    triangles[b],
                    size=self.out_size,
                    padding_mode=self.padding_mode,
                    extra=mattes,
                )
                for b in range(B)
            ]
            out, warped = torch.cat([p[0] for p in pairs]), torch.cat([p[1] for p in pairs])
        out = out.clamp_(0, 1)
        if fill:
            fill_frames(out, warped[:, 0])
        return out, warped, coeffs


def matte_planes(mattes: torch.Tensor, *, head: np.ndarray, filled: np.ndarray) -> None:
    """One frame's warped mattes ``(2, H, W)`` (validity, head) into the float16 planes ``head``
    and ``filled`` (``1 - validity``, clipped to [0, 1]), converted by OpenCV (numpy's float16
    conversion is a slow scalar loop)."""
    import cv2

    planes = mattes.permute(1, 2, 0).cpu().numpy()  # (H, W, 2); on the CPU a view of channels-last memory
    head[...] = cv2.multiply(np.ascontiguousarray(planes[..., 1]), 1.0, dtype=cv2.CV_16F)
    missing = cv2.max(cv2.subtract(1.0, np.ascontiguousarray(planes[..., 0])), 0.0)
    filled[...] = cv2.multiply(missing, 1.0, dtype=cv2.CV_16F)


def fill_frames(rgba: torch.Tensor, valid: torch.Tensor) -> None:
    """Fill, in place, the colour of the missing pixels by their ``valid`` (B, H, W)
    (:func:`stages.fill.fill_regions`, region by region); frames with no pixel less than half real
    are left as they are."""
    from stages.fill import fill_regions

    for b in range(len(rgba)):
        if float(valid[b].min()) >= 0.5:
            continue
        frame = rgba[b].permute(1, 2, 0)  # (H, W, 4): on the CPU a view of channels-last memory
        image = frame.numpy() if frame.device.type == "cpu" else frame.cpu().numpy()
        fill_regions(image, np.ascontiguousarray(valid[b].cpu().numpy()))
        if frame.device.type != "cpu":
            frame.copy_(torch_from(image, rgba))


def torch_from(array: np.ndarray, like: torch.Tensor) -> torch.Tensor:
    """``array`` as a tensor of ``like``'s dtype on its device."""
    import torch

    return torch.from_numpy(np.ascontiguousarray(array)).to(device=like.device, dtype=like.dtype)


@dataclass(frozen=True)
class HeadTurn:
    """The head's rigid motion per frame and the target's depths (a ``head3d`` bundle's fields).

    ``R (B, 3, 3)``, ``t (B, 3)`` mm: ``X' = R X + t`` in the pack camera's frame; ``depth (N,)`` mm
    the camera depth of each feature point before the motion; ``camera (3, 3)`` the pack camera's
    intrinsics, px.
    """

    R: np.ndarray
    t: np.ndarray
    depth: np.ndarray
    camera: np.ndarray

    def frames(self, index: slice) -> HeadTurn:
        """The same motion for the frames ``index`` only."""
        return HeadTurn(self.R[index], self.t[index], self.depth, self.camera)


class Synthesize(FrameStage):
    """``synthesis.synthesize``: target geometry per frame -> expression images (Sec. 6-8, 11).

    Outputs ``frames`` (the whole frame, sRGB half floats), ``mask`` (face alpha), ``head_matte``
    (head matte), ``filled`` (how much of each pixel is filled because no real source pixel covers it:
    beyond the pack image or its validity matte) and ``coeffs``. Head motion (``head_motion``):
    ``depth`` the depth-aware warp of the whole image turned by input ``head``
    (:mod:`stages.synthesis.turn`), ``similarity`` the 2D similarity of eq. 8-9 (input
    ``similarity``), ``none``; ``auto`` is ``depth`` when ``head`` is connected, else ``similarity``
    when that is, else ``none``.
    """

    name = "synthesis.synthesize"
    version = "9"
    doc = (
        "per-subregion QP + compositing + blending + warp (head turned in depth): target points per frame -> "
        "half-float sRGB frames, face mask, head matte, filled matte, coefficients"
    )
    inputs = {
        "model": SYNTHESIS_MODEL,
        "points": POINTS,
        "displacements": DISPLACEMENTS,
        "similarity": SIMILARITY,
        "performer": DISPLACEMENTS,
        "head": HEAD3D,
    }
    optional_inputs = frozenset({"points", "displacements", "similarity", "performer", "head"})
    outputs = {"frames": "frames", "mask": "frames", "head_matte": "frames", "filled": "frames", "coeffs": SYNTHESIS_COEFFS}
    params = (
        Param(
            "mode",
            str,
            "full",
            "full: per-subregion synthesis; global: one combination (Pighin); warp-only: neutral warped",
            MODES,
        ),
        Param(
            "min_coeff",
            float,
            MIN_COEFF,
            "coefficients at or below this are skipped in compositing (then renormalised; the weights made coherent in time spread over more examples: 0.01 drops 0.3 % of their mass and a sixth of the compositing)",
            min=0.0,
            max=1.0,
        ),
        Param(
            "head_motion",
            str,
            "auto",
            "depth: the whole image turned in 3D by input 'head'; similarity: the 2D similarity "
            "(eq. 8-9) of input 'similarity'; none; auto: depth with 'head', else similarity with 'similarity'",
            HEAD_MOTION,
        ),
        Param(
            "head_motion_scale",
            float,
            1.0,
            "similarity mode: multiplies the carried head translation (on top of the face-size ratio from 'performer')",
            min=-100.0,
            max=100.0,
        ),
        Param(
            "width",
            int,
            0,
            "output width, px (the height keeps the pack's aspect ratio); 0: the pack's size; the "
            f"output at most {MAX_OUTPUT_PIXELS / 1e6:.1f} MP (the memory a run takes: docs/synthesis.md)",
            min=0,
            max=MAX_OUTPUT_WIDTH,
        ),
        Param(
            "upscale",
            bool,
            False,
            "allow an output that enlarges the footage the pack was cut from (warned); without it such a size is refused",
        ),
        Param("fps", float, 30.0, "frame rate when the points bundle carries none", min=1e-3, max=1000.0),
        Param(
            "detail_power",
            float,
            DETAIL_POWER,
            "band-pass blending: detail band weights are the coefficients to this power, renormalised (1 = plain eq. 6)",
            min=1.0,
            max=100.0,
        ),
        Param(
            "detail_sigma_px",
            float,
            DETAIL_SIGMA_PX,
            "band-pass blending: Gaussian sigma separating the detail band, px",
            min=0.1,
            max=1000.0,
        ),
        Param(
            "ridge_px",
            float,
            RIDGE_PX,
            "coefficient regularisation of the QPs: n_R tau^2 ||c||^2 with tau this many px (0 = plain eq. 2)",
            min=0.0,
            max=1000.0,
        ),
        Param(
            "teeth_power",
            float,
            TEETH_POWER,
            "the teeth examples' coefficients to this power, renormalised: an even "
            "blend of two shows their teeth doubled (1 = as solved)",
            min=1.0,
            max=100.0,
        ),
        Param(
            "coherence_frames",
            float,
            COHERENCE_FRAMES,
            "example weights coherent in time: sigma of the bilateral filter over frames "
            "(stages.synthesis.coherence; 0 = each frame's own QP solution)",
            min=0.0,
            max=10.0,
        ),
        Param(
            "coherence_size",
            float,
            COHERENCE_SIZE,
            "example weights coherent in time: sigma of the filter's geometry term, "
            "fraction of the face size (RMS distance of the target neutral's points from their centroid; a subregion "
            "that moves more than this between frames keeps its own weights)",
            min=1e-4,
            max=1.0,
        ),
    )

    # Chunks are synthesized on several threads at once: the synthesizer made in open is shared,
    # read-only but for its per-thread buffers and its memo's lock (Synthesizer).
    threading = "reentrant"

    def __init__(self) -> None:
        self._synth: Synthesizer | None = None

    def _output_size(self, model: Mapping[str, np.ndarray], params: Mapping[str, Any]) -> tuple[tuple[int, int], str]:
        """``(W, H)`` of the output and the note on it (:func:`output_size`); StageError for a
        size the footage does not hold."""
        try:
            return output_size(model, int(params["width"]), upscale=bool(params["upscale"]))
        except ValueError as exc:
            raise StageError(f"{self.name}: parameter 'width': {exc}") from None

    def stream_info(self, inputs: Mapping[str, Any], params: Mapping[str, Any]) -> StreamInfo:
        xy, bundle = target_geometry(inputs, stage=self.name)
        fps = float(bundle["fps"]) if "fps" in bundle else float(params["fps"])
        (W, H), _ = self._output_size(inputs["model"], params)
        return StreamInfo(frames=len(xy), fps=fps, width=W, height=H)

    def open(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> None:
        """Prepare the target's model on ``ctx.device`` (:class:`Synthesizer`) for every chunk of the run."""
        size, _ = self._output_size(inputs["model"], params)
        self._synth = Synthesizer(
            inputs["model"],
            device=ctx.device,
            detail_power=float(params["detail_power"]),
            detail_sigma_px=float(params["detail_sigma_px"]),
            ridge_px=float(params["ridge_px"]),
            teeth_power=float(params["teeth_power"]),
            output_size=size,
        )

    def close(self, ctx: Context) -> None:
        self._synth = None

    def _motion(
        self, inputs: Mapping[str, Any], params: Mapping[str, Any], start: int, stop: int
    ) -> tuple[np.ndarray | None, HeadTurn | None, dict[str, Any]]:
        """The chunk's head motion: a 2D similarity (with its centres and scale) or a turn in depth."""
        mode = params["head_motion"]
        head, sim = inputs.get("head"), inputs.get("similarity")
        if mode == "auto":
            mode = "depth" if head is not None else "similarity" if sim is not None else "none"
        if mode == "depth":
            if head is None:
                raise StageError(f"{self.name}: head_motion=depth needs input 'head' (render3d.head's head3d)")
            return None, head_turn(head, inputs["model"], start, stop, stage=self.name), {}
        if mode != "similarity" or sim is None:
            return None, None, {}
        model = inputs["model"]
        options: dict[str, Any] = {"motion_scale": float(params["head_motion_scale"])}
        similarity = np.asarray(sim["params"], np.float64)[start:stop].copy()
        valid = np.asarray(sim["valid"], bool)[start:stop] if "valid" in sim else np.ones(len(similarity), bool)
        similarity[~valid] = (1.0, 0.0, 0.0, 0.0)
        performer = inputs.get("performer")
        if performer is not None:
            if "neutral" not in performer or "names" not in performer:
                raise StageError(
                    f"{self.name}: input 'performer' needs the fields 'neutral' and 'names' (compensate.similarity's displacements)"
                )
            source_center, target_center, ratio = head_motion_frame(
                performer["neutral"], performer["names"], model["neutral_points"], model["point_names"]
            )
            options.update(source_center=source_center, target_center=target_center, motion_scale=options["motion_scale"] * ratio)
        return similarity, None, options

    def process(
        self, start: int, stop: int, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context
    ) -> dict[str, Any]:
        xy, _ = target_geometry(inputs, stage=self.name)
        points = xy[start:stop]
        if not np.isfinite(points).all():
            raise StageError(f"synthesis.synthesize: the input geometry has non-finite points in frames {start}-{stop - 1}")
        similarity, turn, options = self._motion(inputs, params, start, stop)
        _, note = self._output_size(inputs["model"], params)
        if note and start == 0:
            ctx.log.warning("%s: %s", self.name, note)
        model = inputs["model"]
        synth = self._synth
        if synth is None:
            raise RuntimeError(f"{self.name}: process before open (runner.lifecycle.opened)")
        coeffs = None
        if params["mode"] != "warp-only":
            import torch

            sigma_px = float(params["coherence_size"]) * rms_radius(np.asarray(model["neutral_points"], np.float64))
            members = np.array(model["subregion_points"], bool)
            if params["mode"] == "global":  # one combination for the face: one geometry term over all its points
                face = ~np.asarray(model["subregion_teeth"], bool)
                members[face] = members[face].any(axis=0)
            coeffs = torch.from_numpy(
                coherent_coefficients(
                    lambda p: synth.coefficients(p, mode=params["mode"]).cpu().numpy(),
                    xy,
                    start,
                    stop,
                    members,
                    sigma_frames=float(params["coherence_frames"]),
                    sigma_px=sigma_px,
                )
            ).to(synth.device)
        frames, mask, head, filled, coeffs = synth.render_half(
            points,
            mode=params["mode"],
            similarity=similarity,
            turn=turn,
            min_coeff=params["min_coeff"],
            coeffs=coeffs,
            progress=ctx.progress,
            **options,
        )
        return {"frames": frames, "mask": mask, "head_matte": head, "filled": filled, "coeffs": {"coeffs": coeffs.cpu().numpy()}}


def head_turn(head: Mapping[str, np.ndarray], model: Mapping[str, np.ndarray], start: int, stop: int, *, stage: str) -> HeadTurn:
    """The :class:`HeadTurn` of frames ``start:stop`` of a ``head3d`` bundle, checked against the model."""
    for key in ("R", "t", "depth", "names", "camera", "size"):
        if key not in head:
            raise StageError(f"{stage}: input 'head' has no field '{key}' (connect render3d.head's head)")
    if [str(n) for n in head["names"]] != [str(n) for n in model["point_names"]]:
        raise StageError(f"{stage}: input 'head' is for another layout than input 'model' (connect one pack's stages)")
    if tuple(int(v) for v in head["size"]) != tuple(int(v) for v in model["size"]):
        raise StageError(f"{stage}: input 'head' is for {tuple(head['size'])} images, the model's are {tuple(model['size'])}")
    R, t = np.asarray(head["R"], np.float64), np.asarray(head["t"], np.float64)
    if len(R) < stop:
        raise StageError(f"{stage}: input 'head' has {len(R)} frames, the geometry more")
    return HeadTurn(R[start:stop], t[start:stop], np.asarray(head["depth"], np.float64), np.asarray(head["camera"], np.float64))


def run_memory_gb(size: tuple[int, int]) -> float:
    """Estimated peak memory, GB, of a run of the bundled pipeline whose output is ``size = (W,
    H)`` px: :data:`RUN_BASE_GB` plus :data:`GB_PER_OUTPUT_MEGAPIXEL` per megapixel."""
    return RUN_BASE_GB + GB_PER_OUTPUT_MEGAPIXEL * size[0] * size[1] / 1e6


def widest_output(size: tuple[int, int]) -> int:
    """The largest output width, px, for pack images of ``size = (W, H)`` whose output has at most
    :data:`MAX_OUTPUT_PIXELS` pixels."""
    W, H = size
    width = int(np.sqrt(MAX_OUTPUT_PIXELS * W / H))
    while width > 1 and width * max(round(H * width / W), 1) > MAX_OUTPUT_PIXELS:
        width -= 1
    return width


def output_size(model: Mapping[str, np.ndarray], width: int, *, upscale: bool) -> tuple[tuple[int, int], str]:
    """The output size for ``width`` (0: the pack's) and a note when it enlarges the footage.

    The footage holds ``1 / source_scale`` output px per pack px (``source_scale``: pack px per
    footage px, the model's); a pack without it (not cut from footage) holds its own size. An
    output wider than that is refused (``ValueError``, with the sizes) unless ``upscale``, when
    the note says so. An output of more than :data:`MAX_OUTPUT_PIXELS` pixels is refused
    (``ValueError``, with its estimated memory, :func:`run_memory_gb`, and the widest that fits).
    """
    W, H = (int(v) for v in model["size"])
    if width in (0, W):
        return (W, H), ""
    size = (width, max(round(H * width / W), 1))
    if size[0] * size[1] > MAX_OUTPUT_PIXELS:
        raise ValueError(
            f"a {size[0]}x{size[1]} output ({size[0] * size[1] / 1e6:.1f} MP) would take about "
            f"{run_memory_gb(size):.1f} GB ({GB_PER_OUTPUT_MEGAPIXEL} GB per output megapixel); at most "
            f"{MAX_OUTPUT_PIXELS / 1e6:.1f} MP fit the {RUN_BUDGET_GB:.0f} GB a run may take: width <= "
            f"{widest_output((W, H))} for the pack's {W}x{H} images"
        )
    scale = float(model["source_scale"]) if "source_scale" in model else float("nan")
    held = W / scale if np.isfinite(scale) else float(W)
    if width <= held * (1 + 1e-9):
        return size, ""
    what = (
        f"the pack's {W}x{H} images hold {held:.0f} px of footage across"
        if np.isfinite(scale)
        else f"the pack's images are {W}x{H} and were not cut from footage"
    )
    line = f"a {size[0]}x{size[1]} output enlarges {width / held:.2f}x what the footage holds ({what})"
    if not upscale:
        raise ValueError(f"{line}; ask for width <= {int(held)} or set upscale: true")
    return size, line + "; upscaled as asked (upscale: true)"
