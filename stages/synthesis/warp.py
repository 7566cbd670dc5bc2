"""Triangulation-based image warping (Sec. 5.2 and the final warp of Sec. 7), batched in torch.

A warp is given by corresponding points in a source and a destination image (the feature points
plus anchor points on or outside the image border, so hair and background follow) and one
triangulation over them. Each destination triangle maps affinely onto its source triangle; the
dense backward map (destination pixel -> source position) is assembled per triangle and applied
bilinearly: on the CPU with :func:`cv2.remap` (about a third of ``grid_sample``'s CPU time; its
1/32 px fixed-point weights change a sample by at most 1/64 of the local difference between
neighbouring pixels), elsewhere (or for tensors that need gradients) with
:func:`torch.nn.functional.grid_sample`.

Coordinates are OpenCV's: x right, y down, pixel centres at integers.
"""

from __future__ import annotations

import numpy as np

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only; imported where used, so that importing this module stays light
    import torch

__all__ = ["Buffers", "scratch", "border_anchors", "triangulate", "triangle_index_map", "backward_map", "warp_images"]

_SHIFT = 8  # sub-pixel bits for cv2.fillConvexPoly
_BORDERS = {
    "border": "BORDER_REPLICATE",
    "zeros": "BORDER_CONSTANT",
    "reflection": "BORDER_REFLECT_101",
}  # grid_sample padding -> cv2


class Buffers:
    """Arrays one thread keeps between warps (``buffers=`` of :func:`warp_images`).

    A warp of a 600x800 frame needs about 20 MB of temporaries (the triangle index, the gathered
    coefficients, the map, the output); allocated afresh for every frame, glibc hands such sizes
    out as new memory mappings (page faults, zeroing, cold caches). :meth:`get` returns the same
    memory for the same name while shape, dtype and device stay. Not thread-safe: one per thread.
    """

    def __init__(self) -> None:
        self._arrays: dict[str, torch.Tensor] = {}

    def get(self, name: str, shape: tuple[int, ...], dtype: torch.dtype, device: str | torch.device = "cpu") -> torch.Tensor:
        """An uninitialised tensor of ``shape``, ``dtype`` on ``device``: the last one of ``name`` when it fits."""
        import torch

        array = self._arrays.get(name)
        if array is None or tuple(array.shape) != tuple(shape) or array.dtype != dtype or array.device != torch.device(device):
            array = self._arrays[name] = torch.empty(shape, dtype=dtype, device=device)
        return array


def scratch(
    buffers: Buffers | None, name: str, shape: tuple[int, ...], dtype: torch.dtype, device: str | torch.device = "cpu"
) -> torch.Tensor:
    """A temporary: ``buffers.get(name, shape, dtype, device)``, or a new tensor when ``buffers`` is None."""
    import torch

    return torch.empty(shape, dtype=dtype, device=device) if buffers is None else buffers.get(name, shape, dtype, device)


def border_anchors(size: tuple[int, int], *, per_side: int = 4, margin: float = 0.0) -> np.ndarray:
    """Anchor points on a rectangle around the image, evenly spaced, corners included.

    Parameters
    ----------
    size : (W, H)
        Image size in px.
    per_side : int
        Number of segments per side (``4 * per_side`` points in all).
    margin : float
        How far outside the image the rectangle lies, as a fraction of the larger image side
        (0 = through the outer pixel edges). A margin keeps the whole output image covered by
        the triangulation when the anchors move (head motion).

    Returns
    -------
    (4 * per_side, 2) float64 array, px.
    """
    W, H = size
    m = margin * max(W, H)
    x0, y0, x1, y1 = -0.5 - m, -0.5 - m, W - 0.5 + m, H - 0.5 + m
    t = np.arange(per_side) / per_side
    top = np.stack([x0 + t * (x1 - x0), np.full_like(t, y0)], 1)
    right = np.stack([np.full_like(t, x1), y0 + t * (y1 - y0)], 1)
    bottom = np.stack([x1 - t * (x1 - x0), np.full_like(t, y1)], 1)
    left = np.stack([np.full_like(t, x0), y1 - t * (y1 - y0)], 1)
    return np.concatenate([top, right, bottom, left])


def triangulate(points: np.ndarray) -> np.ndarray:
    """Delaunay triangulation of the reference points (feature points plus anchors).

    Parameters
    ----------
    points : (P, 2) array, px

    Returns
    -------
    (K, 3) int32 array of point indices; duplicate points are left out of every triangle and
    zero-area triangles are dropped.
    """
    from scipy.spatial import Delaunay

    tri = Delaunay(np.asarray(points, dtype=np.float64)).simplices.astype(np.int32)
    p = points[tri]
    area = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 2, 0] - p[:, 0, 0]) * (p[:, 1, 1] - p[:, 0, 1])
    return tri[np.abs(area) > 1e-9]


def triangle_index_map(
    points: np.ndarray, triangles: np.ndarray, size: tuple[int, int], *, uncovered: int = -1, out: np.ndarray | None = None
) -> np.ndarray:
    """Which triangle covers each pixel centre of an image.

    Parameters
    ----------
    points : (P, 2) array
        Vertex positions in this image, px.
    triangles : (K, 3) int array
    size : (W, H)
    uncovered : int
        The value of the pixels no triangle covers.
    out : (H, W) int32 C-contiguous array, optional
        Written instead of a new array.

    Returns
    -------
    (H, W) int32 array (``out`` when given): triangle index, ``uncovered`` where no triangle
    covers the pixel. Where triangles overlap (fold-overs) the later one wins; zero-area
    triangles cover nothing.
    """
    import cv2

    W, H = size
    if out is None:
        out = np.empty((H, W), dtype=np.int32)
    elif out.shape != (H, W) or out.dtype != np.int32 or not out.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous ({H}, {W}) int32 array, got {out.shape} {out.dtype}")
    index = out
    index.fill(uncovered)
    verts = np.round(np.asarray(points, dtype=np.float64)[triangles] * (1 << _SHIFT))
    verts = np.clip(verts, -(1 << 30), 1 << 30).astype(np.int32)
    e1, e2 = (verts[:, 1] - verts[:, 0]).astype(np.int64), (verts[:, 2] - verts[:, 0]).astype(np.int64)
    area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    for k in np.flatnonzero(area != 0):
        cv2.fillConvexPoly(index, verts[k], int(k), lineType=cv2.LINE_8, shift=_SHIFT)
    return index


def _dst_to_src_affines(src: torch.Tensor, dst: torch.Tensor, triangles: torch.Tensor) -> torch.Tensor:
    """(B, K, 2, 3) affine maps taking each destination triangle onto its source triangle."""
    import torch

    s = src[:, triangles]  # (B, K, 3, 2)
    d = dst[:, triangles]
    ones = torch.ones(d.shape[:-1] + (1,), dtype=d.dtype, device=d.device)
    D = torch.cat([d, ones], -1).transpose(-1, -2)  # (B, K, 3, 3): columns are [x, y, 1]
    det = torch.linalg.det(D)
    D = torch.where(det.abs()[..., None, None] > 1e-12, D, torch.eye(3, dtype=D.dtype, device=D.device))
    return s.transpose(-1, -2) @ torch.linalg.inv(D)


def backward_map(
    src_points: torch.Tensor,
    dst_points: torch.Tensor,
    triangles: np.ndarray,
    size: tuple[int, int],
    *,
    dtype: torch.dtype | None = None,
    source_size: tuple[int, int] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Dense backward map of a piecewise-affine warp: for each destination pixel, its source position.

    Parameters
    ----------
    src_points, dst_points : (B, P, 2) float tensors
        Corresponding points (feature points and anchors) in the source and destination images, px.
    triangles : (K, 3) int array
        One triangulation shared by both point sets (see :func:`triangulate`).
    size : (W, H)
        Destination image size.
    dtype : torch.dtype, optional
        Precision of the per-pixel map, default ``torch.float32`` (the per-triangle affines are
        always solved in float64).
    source_size : (W_src, H_src), optional
        When given, the map is returned in ``grid_sample``'s normalised coordinates for a source
        image of that size (``align_corners=True``: -1 and 1 are the centres of the outer
        pixels) instead of pixels; the normalisation is folded into the per-triangle affines.

    Returns
    -------
    map : (B, H, W, 2) tensor of ``dtype``
        Source (x, y) per destination pixel (px, or normalised with ``source_size``).
    covered : (B, H, W) bool tensor
        False where no destination triangle covers the pixel (the map is the identity there).
    """
    import torch

    dtype = torch.float32 if dtype is None else dtype
    W, H = size
    covered = torch.empty(src_points.shape[0], H, W, dtype=torch.bool, device=src_points.device)
    return _source_map(src_points, dst_points, triangles, size, dtype=dtype, source_size=source_size, covered=covered), covered


def _source_map(
    src_points: torch.Tensor,
    dst_points: torch.Tensor,
    triangles: np.ndarray,
    size: tuple[int, int],
    *,
    dtype: torch.dtype,
    source_size: tuple[int, int] | None,
    covered: torch.Tensor | None = None,
    buffers: Buffers | None = None,
) -> torch.Tensor:
    """The backward map, (B, H, W, 2) source (x, y) interleaved (``cv2.remap``'s two-channel map).

    Per pixel, the covering triangle's affine ``[[a0, a1, a2], [a3, a4, a5]]`` applied to the
    pixel centre ``(x, y)``: ``x_src = (a2 + a0 x) + a1 y``, ``y_src = (a5 + a3 x) + a4 y``.
    The coefficients are gathered in pairs, ``(a0, a3)``, ``(a1, a4)``, ``(a2, a5)``, one pair
    per gathered element (two float32 gathered as one int64: three 1-D gathers of the pixel
    index instead of six, the pairs landing interleaved as the map is), frame by frame so that
    the index stays in cache; pixels no triangle covers index an identity row. When given,
    ``covered`` (B, H, W) bool is filled with whether a triangle covers the pixel. With
    ``buffers`` the temporaries and the returned map are ``buffers``' arrays. See
    :func:`backward_map` for the other parameters.
    """
    import torch

    W, H = size
    device = src_points.device
    B = src_points.shape[0]
    tri = torch.as_tensor(np.asarray(triangles), dtype=torch.long, device=device)
    affines = _dst_to_src_affines(src_points.to(torch.float64), dst_points.to(torch.float64), tri)  # (B, K, 2, 3)
    K = affines.shape[1]
    identity = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64, device=device)
    affines = torch.cat([affines, identity.expand(B, 1, 2, 3)], 1)
    if source_size is not None:
        sw, sh = source_size
        scale = torch.tensor([2.0 / max(sw - 1, 1), 2.0 / max(sh - 1, 1)], dtype=torch.float64, device=device)
        affines = affines * scale[:, None]
        affines[..., 2] -= 1.0
    pairs = affines.to(dtype).permute(0, 3, 1, 2).contiguous()  # (B, 3, K + 1, 2): (x, y) coefficient pairs
    if pairs.element_size() == 4:
        pairs = pairs.view(torch.int64)[..., 0]  # a float32 pair as one element: (B, 3, K + 1)
    gathered = scratch(buffers, "gathered", (3, H * W) + pairs.shape[3:], pairs.dtype, device)
    index_out = scratch(buffers, "index", (H, W), torch.int32).numpy()
    xs = (
        torch.arange(W, dtype=dtype, device=device).view(1, W, 1).expand(1, W, 2).contiguous()
    )  # (1, W, 2): no stride-0 inner axis
    ys = torch.arange(H, dtype=dtype, device=device).view(H, 1, 1)
    maps = scratch(buffers, "map", (B, H, W, 2), dtype, device)
    for b, d in enumerate(dst_points.detach().to(torch.float64).cpu().numpy()):  # frame by frame: the index stays in cache
        index = triangle_index_map(d, triangles, size, uncovered=K, out=index_out)  # uncovered pixels: the identity
        if covered is not None:
            covered[b] = torch.from_numpy(index != K)
        index = torch.from_numpy(index).to(device).flatten()  # int32: index_select takes it as it is
        for j in range(3):  # 1-D gathers: about half the time of one gather along dim 1 of (3, K + 1)
            torch.index_select(pairs[b, j], 0, index, out=gathered[j])
        a0, a1, a2 = gathered.view(dtype).view(3, H, W, 2)
        torch.addcmul(a2, a0, xs, out=maps[b]).addcmul_(a1, ys)
    return maps


def warp_images(
    images: torch.Tensor,
    src_points: torch.Tensor,
    dst_points: torch.Tensor,
    triangles: np.ndarray,
    *,
    size: tuple[int, int] | None = None,
    padding_mode: str = "border",
    buffers: Buffers | None = None,
    extra: torch.Tensor | None = None,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Warp images so that ``src_points`` move to ``dst_points`` (piecewise affine, bilinear).

    Parameters
    ----------
    images : (B, C, H, W) float tensor
        Source images (``B = 1`` is broadcast over the point batch).
    src_points, dst_points : (B, P, 2) tensors, px
        Corresponding points, anchors included.
    triangles : (K, 3) int array
        Triangulation over the points.
    size : (W, H), optional
        Output size; the source size when omitted.
    padding_mode : ``"border" | "zeros" | "reflection"``
        ``grid_sample`` padding for source positions outside the image (on the CPU the
        matching ``cv2.BORDER_REPLICATE``, ``BORDER_CONSTANT`` 0, ``BORDER_REFLECT_101``).
    buffers : Buffers, optional
        CPU path: this thread's :class:`Buffers` for the temporaries and the output, which the
        next call with the same buffers overwrites; ignored elsewhere.
    extra : (1 or B, C2, H, W) float32 tensor, optional
        Further planes of the source (mattes) warped by the same map, positions outside the
        source reading 0 whatever ``padding_mode`` (a matte says what the source holds there:
        nothing).

    Returns
    -------
    (B, C, H_out, W_out) tensor, float64 for float64 images, float32 otherwise. On the CPU its
    memory is channels-last (``permute(0, 2, 3, 1)`` of it is contiguous, no copy). With
    ``extra``, the pair (that, the warped ``extra`` (B, C2, H_out, W_out) float32).
    """
    import torch

    _, C, H, W = images.shape
    size = size or (W, H)
    if padding_mode not in _BORDERS:
        raise ValueError(f"padding_mode must be one of {tuple(_BORDERS)}, got {padding_mode!r}")
    dtype = torch.float64 if images.dtype == torch.float64 else torch.float32
    if images.device.type != "cpu" or images.requires_grad:
        import torch.nn.functional as F

        grid, _ = backward_map(src_points, dst_points, triangles, size, dtype=dtype, source_size=(W, H))
        if images.shape[0] == 1 and grid.shape[0] > 1:
            images = images.expand(grid.shape[0], -1, -1, -1)
        out = F.grid_sample(images, grid, mode="bilinear", padding_mode=padding_mode, align_corners=True)
        if extra is None:
            return out
        planes = extra.expand(grid.shape[0], -1, -1, -1) if extra.shape[0] == 1 else extra
        return out, F.grid_sample(planes.to(grid.dtype), grid, mode="bilinear", padding_mode="zeros", align_corners=True).float()
    import cv2

    maps = _source_map(src_points, dst_points, triangles, size, dtype=torch.float32, source_size=None, buffers=buffers)
    B, (Wo, Ho) = maps.shape[0], size
    source = images.detach().to(dtype).permute(0, 2, 3, 1)  # (B or 1, H, W, C); no copy when channels-last
    out = scratch(buffers, "warped", (B, Ho, Wo, C), dtype)
    planes = out.numpy()
    for b in range(B):
        image = source[b if len(source) > 1 else 0].contiguous().numpy()
        cv2.remap(
            image,
            maps[b].numpy(),
            None,
            cv2.INTER_LINEAR,
            dst=planes[b] if C > 1 else planes[b, ..., 0],
            borderMode=getattr(cv2, _BORDERS[padding_mode]),
        )
    if extra is None:
        return out.permute(0, 3, 1, 2)
    C2 = extra.shape[1]
    more = extra.detach().float().permute(0, 2, 3, 1)
    warped = scratch(buffers, "warped_extra", (B, Ho, Wo, C2), torch.float32)
    for b in range(B):
        plane = more[b if len(more) > 1 else 0].contiguous().numpy()
        cv2.remap(
            plane,
            maps[b].numpy(),
            None,
            cv2.INTER_LINEAR,
            dst=warped[b].numpy() if C2 > 1 else warped[b, ..., 0].numpy(),
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
    return out.permute(0, 3, 1, 2), warped.permute(0, 3, 1, 2)
