"""Geometry of an edit: propagated edits (Sec. 10, 13), in-betweens (Sec. 14.2), keyframes.

All geometries are ``(N, 2)`` (or ``(T, N, 2)``) float64 pixel positions of the layout's feature
points, x right, y down, origin at the centre of the top-left pixel, in the target neutral's
frame (no head motion), the frame of a run's ``data.npz`` ``target_xy``.
"""

from __future__ import annotations

from typing import Callable, Mapping

import numpy as np

from stages.propagation.hierarchical_pca import HierarchicalPCA
from stages.propagation.propagate import propagate_edit

INBETWEENS = 5  # in-between frames from the previous to the current geometry (Sec. 14.2)


def edited_geometry(
    model: HierarchicalPCA,
    pinned: Mapping[int, np.ndarray],
    *,
    base: np.ndarray | None = None,
    propagate: Callable[..., np.ndarray] = propagate_edit,
) -> np.ndarray:
    """The most likely geometry given the points the user pinned (Sec. 13, propagation Sec. 10.1).

    Parameters
    ----------
    model : HierarchicalPCA
        The target's hierarchical PCA (``propagate.train``).
    pinned : dict {point index: (2,) px}
        Points the user dragged or pinned, at their positions.
    base : (N, 2) float, optional
        The geometry being touched up (a performance frame). ``None``: the edit starts from the
        neutral and the result is motion propagation of the pinned points' displacements from the
        neutral, exactly as the paper. With a base, the pinned points' displacements from the
        base are propagated and added to it: ``base + P(d) - P(0)``, where ``P`` propagates
        displacements given at the pinned points; subtracting ``P(0)`` (the same pinned set held
        still) keeps the base where nothing was moved, so unmoved pins leave the base unchanged.
    propagate : callable
        ``propagate(model, current_points, fixed) -> (N, 2)``: :func:`propagate_edit` (the
        default), or :class:`stages.propagation.pinned.PinnedPropagation` (the same, faster while the
        pinned set stays the same).

    Returns
    -------
    (N, 2) float64
        Pinned points exactly where they were put, the others at their inferred positions.
        With no pinned point, the base (or the neutral).

    Raises
    ------
    ValueError
        ``base`` is not ``(N, 2)`` finite, a pinned index is outside ``0..N-1`` or a position
        is not a finite ``(2,)``.
    """
    neutral = model.neutral
    n = model.n_points
    start = neutral if base is None else np.asarray(base, np.float64)
    if start.shape != (n, 2) or not np.isfinite(start).all():
        raise ValueError(f"base must be a finite ({n}, 2) geometry, got shape {start.shape}")
    moved: dict[int, np.ndarray] = {}
    for index, xy in pinned.items():
        if not 0 <= int(index) < n:
            raise ValueError(f"pinned point index must be in 0..{n - 1}, got {index}")
        xy = np.asarray(xy, np.float64)
        if xy.shape != (2,) or not np.isfinite(xy).all():
            raise ValueError(f"pinned point {index}: expected a finite (x, y), got {xy!r}")
        moved[int(index)] = xy
    if not moved:
        return start.copy()
    if base is None:
        return propagate(model, neutral, moved)
    shifted = propagate(model, neutral, {i: neutral[i] + xy - start[i] for i, xy in moved.items()})
    held = propagate(model, neutral, {i: neutral[i] for i in moved})
    result = start + shifted - held
    for i, xy in moved.items():
        result[i] = xy
    return result


def interpolate_keyframes(times_s: np.ndarray, geometries: np.ndarray, *, fps: float) -> np.ndarray:
    """Keyframe geometries sampled at ``fps`` by linear interpolation in time.

    Parameters
    ----------
    times_s : (K,) float
        Keyframe times, s, strictly increasing.
    geometries : (K, N, 2) float
        Keyframe geometries, px.
    fps : float
        Output frame rate, frames/s (> 0).

    Returns
    -------
    (T, N, 2) float64
        Frame ``k`` at ``times_s[0] + k / fps``, ``T = floor((times_s[-1] - times_s[0]) fps) + 1``
        (the last keyframe is the last frame when the span is a whole number of frames); one
        keyframe gives one frame.

    Raises
    ------
    ValueError
        Shapes disagree, values are not finite, times do not increase or ``fps <= 0``.
    """
    times = np.asarray(times_s, np.float64)
    geoms = np.asarray(geometries, np.float64)
    if times.ndim != 1 or len(times) == 0 or geoms.shape[:1] != times.shape or geoms.ndim != 3 or geoms.shape[2] != 2:
        raise ValueError(f"expected times (K,) and geometries (K, N, 2) with K >= 1, got {times.shape} and {geoms.shape}")
    if not (np.isfinite(times).all() and np.isfinite(geoms).all()):
        raise ValueError("keyframe times and geometries must be finite")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a finite number > 0, got {fps!r}")
    if (np.diff(times) <= 0).any():
        raise ValueError(f"keyframe times must increase strictly, got {times.tolist()}")
    if len(times) == 1:
        return geoms.copy()
    count = int(np.floor((times[-1] - times[0]) * fps + 1e-9)) + 1
    t = times[0] + np.arange(count) / fps
    upper = np.clip(np.searchsorted(times, t, side="right"), 1, len(times) - 1)
    lower = upper - 1
    w = ((t - times[lower]) / (times[upper] - times[lower]))[:, None, None]
    return (1.0 - w) * geoms[lower] + w * geoms[upper]


def inbetweens(previous: np.ndarray, current: np.ndarray, *, count: int = INBETWEENS) -> np.ndarray:
    """The in-between geometries from ``previous`` to ``current`` (Sec. 14.2: five, linear).

    Parameters
    ----------
    previous, current : (N, 2) float, px
    count : int
        In-betweens, excluding both ends (>= 1).

    Returns
    -------
    (count, N, 2) float64, at fractions ``k / (count + 1)``, ``k = 1..count``.
    """
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    pair = np.stack([np.asarray(previous, np.float64), np.asarray(current, np.float64)])
    return interpolate_keyframes(np.array([0.0, count + 1.0]), pair, fps=1.0)[1:-1]
