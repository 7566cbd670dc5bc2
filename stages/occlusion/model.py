"""The clip's own appearance model of each region, and the per-frame visibility of its structure.

The model of a region is a template strip ``T`` (:mod:`stages.occlusion.profiles`): the
element-wise median of its strips over the frames where the region is seen. A frame's
*visibility* is the least-squares weight of the template in its strip,
``v_t = <x_t, T> / <T, T>`` (both mean-free per channel), divided by its median over the seen
frames: 1.0 is the region's structure at the strength typical of the clip, 0 is none of it (a
hand, a sleeve, a uniform surface where the landmarks put the region), negative the structure
inverted. Because the strip follows the landmarks, an expression moves the template with the
contour instead of breaking it; because the channels are contrasts, the light's level and colour
cancel.

Which frames are *seen* is estimated, not assumed: the first template is the median over the
half of the frames whose strips carry the most structure (energy ``<x_t, x_t>``; an occluder is
smoother than the face's structure, so a clip occluded for most of its length still starts from
face frames), then it is re-estimated from the frames whose visibility exceeds ``keep``, a few
times. No frame of the clip is privileged, so a clip that starts occluded is judged like any other.
"""

from __future__ import annotations

import numpy as np

#: Fewest frames a template is estimated from; with fewer seen frames the previous one stays.
MIN_FRAMES = 5


def template(strips: np.ndarray, *, keep: float, iterations: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """The region's template and the frames it was estimated from.

    Parameters
    ----------
    strips : (F, D) float
        The region's mean-free strips of the frames with a face, flattened.
    keep : float
        Visibility above which a frame counts as seen when re-estimating.
    iterations : int
        Re-estimations after the first template.

    Returns
    -------
    template : (D,) float64
    seen : (F,) bool
        The frames of the last estimate.
    """
    x = np.asarray(strips, np.float64)
    energy = np.einsum("fd,fd->f", x, x)
    seen = energy >= np.median(energy)
    t = np.median(x[seen], axis=0)
    for _ in range(iterations):
        now = visibility(x, t, seen) > keep
        if now.sum() < MIN_FRAMES:
            break
        seen, t = now, np.median(x[now], axis=0)
    return t, seen


def visibility(strips: np.ndarray, t: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """``v_t`` of the module doc for each frame ``(F,)``: the template's weight in each strip over
    its median in the ``seen`` frames."""
    x = np.asarray(strips, np.float64)
    weight = x @ t / max(float(t @ t), 1e-12)
    level = float(np.median(weight[seen])) if seen.any() else 0.0
    return weight / level if level > 1e-9 else np.zeros_like(weight)


def median_filter(values: np.ndarray, width: int) -> np.ndarray:
    """Running median over ``width`` (odd) consecutive values ``(F,)``, the ends repeated."""
    if width <= 1 or len(values) == 0:
        return np.asarray(values, np.float64)
    half = width // 2
    padded = np.pad(np.asarray(values, np.float64), half, mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, width)
    return np.median(windows, axis=1)
