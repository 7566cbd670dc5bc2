"""Correlation-tracking primitives (paper Sec. 14.1): gray conversion, correlation peaks with
sub-pixel refinement, local affine motion from neighbours, patch sampling, carrying lost points
along with the face.

Pixel convention: x right, y down, origin at the centre of the top-left pixel.
"""

from __future__ import annotations

import functools

import numpy as np

from stages.color import luma_opencv
from stages.geometry.similarity import apply_similarity, fit_similarity


def intensity(frame: np.ndarray) -> np.ndarray:
    """An ``(H, W)``, ``(H, W, 1)`` or RGB ``(H, W, 3)`` frame as the ``(H, W)`` float32 image the
    trackers match, in the frame's own intensity units (RGB: :func:`stages.color.luma_opencv`)."""
    if frame.ndim == 3 and frame.shape[2] == 3:
        frame = luma_opencv(frame)
    elif frame.ndim == 3:
        frame = frame[..., 0]
    return np.asarray(frame, dtype=np.float32)


def inside(xy: np.ndarray, width: int, height: int) -> np.ndarray:
    """``(..., 2)`` positions -> ``(...)`` bool, True for positions on the image ``[0, W-1] x [0, H-1]``."""
    return (xy[..., 0] >= 0) & (xy[..., 0] <= width - 1) & (xy[..., 1] >= 0) & (xy[..., 1] <= height - 1)


def correlation_peaks(response: np.ndarray, *, exclude: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel peaks, peak values and peak-to-sidelobe ratios of a stack of correlation surfaces.

    Parameters
    ----------
    response : (N, S, S) float
        Correlation surfaces (e.g. ``cv2.TM_CCOEFF_NORMED`` outputs); cell ``(j, i)`` is the score
        of a displacement ``(i - (S-1)/2, j - (S-1)/2)`` px from the window centre.
    exclude : int
        Half-size of the square around the peak left out of the sidelobe (MOSSE's PSR).

    Returns
    -------
    offset : (N, 2) float64
        Peak displacement ``(dx, dy)`` in px from the window centre; the sub-pixel part comes from
        a parabola through the peak and its two neighbours along each axis (zero on the border).
    peak : (N,) float64
        Peak value.
    psr : (N,) float64
        ``(peak - mean(sidelobe)) / std(sidelobe)``.
    """
    n, s, _ = response.shape
    flat = response.reshape(n, s * s).astype(np.float64)
    arg = flat.argmax(axis=1)
    py, px = np.divmod(arg, s)
    rows = np.arange(n)
    peak = flat[rows, arg]

    def parabola(minus: np.ndarray, plus: np.ndarray, at_edge: np.ndarray) -> np.ndarray:
        curvature = minus - 2.0 * peak + plus
        ok = (~at_edge) & (curvature < 0)
        shift = np.where(ok, 0.5 * (minus - plus) / np.where(ok, curvature, -1.0), 0.0)
        return np.clip(shift, -0.5, 0.5)

    surface = response.astype(np.float64)
    edge_x = (px == 0) | (px == s - 1)
    edge_y = (py == 0) | (py == s - 1)
    sub_x = parabola(surface[rows, py, np.maximum(px - 1, 0)], surface[rows, py, np.minimum(px + 1, s - 1)], edge_x)
    sub_y = parabola(surface[rows, np.maximum(py - 1, 0), px], surface[rows, np.minimum(py + 1, s - 1), px], edge_y)
    centre = (s - 1) / 2.0
    offset = np.stack([px - centre + sub_x, py - centre + sub_y], axis=1)

    grid = np.arange(s)
    near = (np.abs(grid[None, :, None] - py[:, None, None]) <= exclude) & (
        np.abs(grid[None, None, :] - px[:, None, None]) <= exclude
    )
    side = ~near.reshape(n, s * s)
    count = side.sum(axis=1)
    mean = (flat * side).sum(axis=1) / count
    var = (((flat - mean[:, None]) ** 2) * side).sum(axis=1) / count
    psr = (peak - mean) / (np.sqrt(var) + 1e-6)
    return offset, peak, psr


def carry_along(last: np.ndarray, found: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """New positions ``(N, 2)``: ``found`` where ``valid``; elsewhere ``last`` moved by the 2D
    similarity (eq. 8-9) that best maps the valid points' ``last`` onto their ``found`` (the head's
    motion), by their translation if only one is valid, not at all if none is."""
    if valid.sum() >= 2:
        moved = apply_similarity(fit_similarity(last[valid], found[valid]), last)
    elif valid.any():
        moved = last + (found[valid] - last[valid])
    else:
        moved = last
    return np.where(valid[:, None], found, moved)


def local_affines(
    src: np.ndarray, dst: np.ndarray, weight: np.ndarray, *, sigma_px: float, ridge: float = 0.05, exclude_self: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Local affine motions of N points: linear parts ``M_i (N, 2, 2)`` and positions ``b_i (N, 2)``.

    For each point ``i``, the affine ``y = M_i (x - src_i) + b_i`` minimizing
    ``sum_j w_ij |M_i (src_j - src_i) + b_i - dst_j|^2 + lambda_i |M_i - M_g|_F^2`` with
    ``w_ij = weight_j exp(-|src_j - src_i|^2 / (2 sigma_px^2))`` (the point's neighbourhood on the
    face), ``lambda_i = ridge * sigma_px^2 * sum_j w_ij`` and ``M_g`` the linear part of the
    unweighted affine fit of all points with ``weight > 0`` (the identity with fewer than 3; pulled
    faintly towards it, so that collinear points give a finite answer), so a
    point with few or collinear neighbours falls back on the face's global motion. With
    ``exclude_self`` the sum leaves ``j = i`` out: ``b_i`` is then where the neighbours alone put
    point ``i``.

    Parameters
    ----------
    src, dst : (N, 2) float
        Positions in the first and in the current frame, px.
    weight : (N,) float
        Trust in each correspondence (0 = unused).
    """
    x = np.column_stack([src, np.ones(len(src))])
    use = weight > 0
    m_global = np.eye(2)
    if use.sum() >= 3:  # least squares, a faint pull to the identity where the points are collinear
        pull = 1e-6 * use.sum() * (src[use].var(axis=0).sum() + 1.0)
        gram = x[use].T @ x[use] + pull * np.diag([1.0, 1.0, 0.0])
        m_global = np.linalg.solve(gram, x[use].T @ dst[use] + pull * np.eye(3, 2))[:2].T
    rel = src[None, :, :] - src[:, None, :]  # (N, N, 2): src_j - src_i
    w = weight[None, :] * np.exp(-(rel**2).sum(axis=2) / (2.0 * sigma_px**2))
    if exclude_self:
        np.fill_diagonal(w, 0.0)
    design = np.concatenate([rel, np.ones(rel.shape[:2] + (1,))], axis=2)  # (N, N, 3)
    weighted = np.transpose(design * w[:, :, None], (0, 2, 1))  # (N, 3, N)
    gram = weighted @ design
    rhs = weighted @ dst
    lam = ridge * sigma_px**2 * w.sum(axis=1)
    gram[:, 0, 0] += lam
    gram[:, 1, 1] += lam
    rhs[:, :2, :] += lam[:, None, None] * m_global.T[None]
    gram[:, 2, 2] += 1e-9
    solution = np.linalg.solve(gram, rhs)
    return np.transpose(solution[:, :2, :], (0, 2, 1)), solution[:, 2, :]


@functools.lru_cache(maxsize=8)
def patch_grid(side: int) -> np.ndarray:
    """Offsets ``(2, side * side)`` px (x row, y row) of the cells of a square patch from its centre,
    row by row."""
    grid = np.arange(side, dtype=np.float32) - (side - 1) / 2.0
    return np.stack([np.tile(grid, side), np.repeat(grid, side)])


def sample_patches(image: np.ndarray, centres: np.ndarray, side: int, linear: np.ndarray | None = None) -> np.ndarray:
    """Square patches ``(N, side, side)`` float32 of ``image`` (bicubic, replicated border): patch
    cell ``(r, c)`` of point ``n`` is the image at ``centres[n] + linear[n] @ (c - h, r - h)``,
    ``h = (side - 1) / 2`` (``linear (N, 2, 2)``: identity if omitted)."""
    import cv2

    ux, uy = patch_grid(side)
    cx, cy = centres.astype(np.float32).T
    if linear is None:
        map_x, map_y = cx[:, None] + ux, cy[:, None] + uy
    else:
        m = linear.astype(np.float32)
        map_x = cx[:, None] + m[:, 0, :1] * ux + m[:, 0, 1:] * uy
        map_y = cy[:, None] + m[:, 1, :1] * ux + m[:, 1, 1:] * uy
    patches = cv2.remap(image, map_x.reshape(-1, side), map_y.reshape(-1, side), cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    return patches.reshape(-1, side, side)
