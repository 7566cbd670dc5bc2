"""The 2D similarity of eq. 8 (Zhang et al. 2006, Sec. 12), ``T(x, y) = [[a, -b], [b, a]] @ (x, y) +
(tx, ty)``: its least-squares fit to point pairs (eq. 9), applying it and its inverse.

The fit has a closed form (the 2D case of Umeyama's / Horn's absolute orientation with scale):
with centroids removed, ``a = sum(x . x') / sum |x|^2`` and ``b = sum(x cross x') / sum |x|^2``,
then the translation from the centroids; an optional robust variant reweights the points
iteratively with Huber weights. Points are px (x right, y down).
"""

from __future__ import annotations

import numpy as np


def fit_similarity(
    src: np.ndarray, dst: np.ndarray, *, weights: np.ndarray | None = None, huber_px: float | None = None, iterations: int = 10
) -> np.ndarray:
    """Least-squares 2D similarity mapping ``src`` onto ``dst`` (eq. 9).

    Parameters
    ----------
    src, dst : (n, 2) float
        Corresponding points in px, ``n >= 2`` (not all coincident).
    weights : (n,) float, optional
        Non-negative weights of the squared residuals (all 1 if omitted).
    huber_px : float, optional
        If given, iteratively reweighted least squares with Huber weights
        ``min(1, huber_px / r_i)`` on the residual lengths ``r_i`` (px), ``iterations`` times.

    Returns
    -------
    (4,) float64
        ``(a, b, tx, ty)`` of eq. 8.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    base = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = base
    for _ in range(1 if huber_px is None else iterations + 1):
        total = w.sum()
        mu_s = (w[:, None] * src).sum(axis=0) / total
        mu_d = (w[:, None] * dst).sum(axis=0) / total
        s, d = src - mu_s, dst - mu_d
        norm = (w * (s**2).sum(axis=1)).sum()
        a = (w * (s * d).sum(axis=1)).sum() / norm
        b = (w * (s[:, 0] * d[:, 1] - s[:, 1] * d[:, 0])).sum() / norm
        t = mu_d - np.array([a * mu_s[0] - b * mu_s[1], b * mu_s[0] + a * mu_s[1]])
        params = np.array([a, b, t[0], t[1]])
        if huber_px is not None:
            r = np.linalg.norm(apply_similarity(params, src) - dst, axis=1)
            w = base * np.minimum(1.0, huber_px / np.maximum(r, 1e-12))
    return params


def apply_similarity(params: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """``T(x)`` of eq. 8 for ``params (4,)`` = (a, b, tx, ty) and points ``xy (..., 2)`` px."""
    a, b, tx, ty = params
    return np.stack([a * xy[..., 0] - b * xy[..., 1] + tx, b * xy[..., 0] + a * xy[..., 1] + ty], axis=-1)


def invert_similarity(params: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """``T^-1(x')`` for ``params (4,)`` and points ``xy (..., 2)`` px."""
    a, b, tx, ty = params
    x, y = xy[..., 0] - tx, xy[..., 1] - ty
    scale = a * a + b * b
    return np.stack([(a * x + b * y) / scale, (-b * x + a * y) / scale], axis=-1)
