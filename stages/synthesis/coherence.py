"""Example weights coherent in time: a joint bilateral filter of the QP coefficients (eq. 2-5).

Each frame's convex combination is the projection of its subregion's points onto the hull of the
example geometries. Where two combinations fit a geometry almost equally well, landmark jitter of
a fraction of a pixel flips the solution from one to the other, and the texture jumps: forehead
lines vanish for a frame while the geometry barely moves. Smoothing the coefficients in time
removes the flips but, done blindly, lags fast expressions (a 3-5-frame mouth opening, whose
texture must follow its geometry). So each subregion's coefficients are averaged over the frames
around, weighted by both the time apart and how alike the subregion's geometry is:

    c~_t^R = sum_s w_ts^R c_s^R / sum_s w_ts^R,
    w_ts^R = exp(-(s - t)^2 / (2 sigma_t^2)) exp(-D_ts^R^2 / (2 sigma_g^2)),   |s - t| <= 3 sigma_t

with ``D_ts^R`` the RMS distance between subregion R's points in frames t and s. While a
subregion holds still, its neighbours count fully and a flip is averaged away; while it moves, the
geometry term shuts the neighbours out and the texture follows frame by frame. A weighted mean of
convex combinations is a convex combination (``c >= 0``, ``sum c = 1`` hold), and the geometry is
untouched: only the texture composited in the standard geometry changes (eq. 6), the warp to the
frame's points is the same.

The filter of frame t reads only the coefficients and points of frames ``t - W .. t + W``
(``W = ceil(3 sigma_t)``), summed in a fixed order, so a frame's result does not depend on the
chunk it is computed in.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

__all__ = ["window_frames", "coherent_coefficients"]


def window_frames(sigma_frames: float) -> int:
    """Half-width ``W`` of the filter, frames: ``ceil(3 sigma_t)`` (0 turns the filter off)."""
    return int(math.ceil(3.0 * sigma_frames)) if sigma_frames > 0 else 0


def coherent_coefficients(
    solve: Callable[[np.ndarray], np.ndarray],
    points: np.ndarray,
    start: int,
    stop: int,
    members: np.ndarray,
    *,
    sigma_frames: float,
    sigma_px: float,
) -> np.ndarray:
    """The filtered coefficients of frames ``start .. stop - 1`` (module docstring).

    Parameters
    ----------
    solve : callable
        ``solve(points (L, N, 2)) -> (L, S, K)`` float64: each frame's own QP coefficients.
    points : (T, N, 2) float
        The target geometry of every frame of the clip, px.
    start, stop : int
        The frames wanted.
    members : (S, N) bool
        Each subregion's points (the synthesis model's ``subregion_points``).
    sigma_frames : float
        ``sigma_t``, frames; 0 returns the frames' own coefficients.
    sigma_px : float
        ``sigma_g``, px of RMS point distance.

    Returns
    -------
    (stop - start, S, K) float64
    """
    points = np.asarray(points, np.float64)
    n_frames = len(points)
    W = window_frames(sigma_frames)
    lo, hi = max(0, start - W), min(n_frames, stop + W)
    raw = np.asarray(solve(points[lo:hi]), np.float64)
    if W == 0:
        return raw[start - lo : stop - lo]
    members = np.asarray(members, np.float64)
    count = np.maximum(members.sum(axis=1), 1.0)  # (S,)
    frames = np.arange(start, stop)
    total = np.zeros((stop - start,) + raw.shape[1:])
    weight_sum = np.zeros((stop - start, raw.shape[1]))
    for k in range(-W, W + 1):  # fixed order: each frame sums its window alike in any chunk
        s = frames + k
        inside = (s >= 0) & (s < n_frames)
        s_safe = np.clip(s, lo, hi - 1)
        step = np.sum((points[frames] - points[s_safe]) ** 2, axis=-1)  # (B, N) px^2
        # (B, S): mean squared point distance per subregion, a per-row sum (a matrix product's
        # rounding would depend on how many frames the chunk holds)
        distance2 = np.sum(step[:, None, :] * members[None], axis=-1) / count
        w = np.exp(-0.5 * k * k / sigma_frames**2 - 0.5 * distance2 / sigma_px**2) * inside[:, None]
        total += w[..., None] * raw[s_safe - lo]
        weight_sum += w
    return total / weight_sum[..., None]
