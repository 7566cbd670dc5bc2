"""The clip's own appearance model of each region, and the per-frame visibility of its structure.

The model of a region is a template strip ``T`` (:mod:`stages.occlusion.profiles`): the
element-wise median of its strips over the frames where the region is seen. A frame's
*visibility* is the least-squares weight of the template in its strip,
``w_t = <x_t, T> / <T, T>`` (both mean-free per channel), taken at the best of the ``2 s + 1``
shifts of the strip along the normals (``s`` = :data:`stages.occlusion.profiles.SHIFT` samples:
the landmarks' contour may be a little off the image's) and divided by its median over the seen
frames: 1.0 is the region's structure at the strength typical of the clip, 0 is none of it (a
hand, a sleeve, a uniform surface where the landmarks put the region), negative the structure
inverted. Because the strip follows the landmarks, an expression moves the template with the
contour instead of breaking it; because the channels are contrasts, the light's level and colour
cancel.

Which frames are *seen* is estimated, not assumed: the first template is the median over the
half of the frames whose strips carry the most structure *across* the contour (the energy of the
strip's profile averaged along the contour: the lips' edge, the lash line, the brow's stripe run
along their contours, while an occluder is smoother, or, like the gaps between fingers, runs
across them), so a clip occluded for half its length or more still starts from face frames; then
it is re-estimated from the frames whose visibility exceeds ``keep``, a few times. No frame of the clip is privileged, so a clip that starts occluded is judged like any other.

A frame whose visibility is below ``keep`` gets a second opinion (:func:`local_visibility`): its
strip against the median of the seen frames whose face has the nearest shape (head pose and
expression from the landmarks), so that a head turned 30 degrees or a grimace is compared with
frames like it; the larger of the two visibilities is kept.
"""

from __future__ import annotations

import numpy as np

#: Fewest frames a template is estimated from; with fewer seen frames the previous one stays.
MIN_FRAMES = 5
#: Most seen frames a local template is looked for among (evenly spread over the clip).
POOL = 1000


def windows(strips: np.ndarray, shift: int) -> np.ndarray:
    """The ``2 shift + 1`` windows of ``M`` normal samples in strips ``(F, K, M + 2 shift, C)``,
    each made mean-free per channel and flattened: ``(F, 2 shift + 1, K M C)``."""
    x = np.asarray(strips, np.float64)
    m = x.shape[2] - 2 * shift
    out = np.stack([x[:, :, j : j + m] for j in range(2 * shift + 1)], axis=1)
    out -= out.mean(axis=(2, 3), keepdims=True)
    return out.reshape(len(x), 2 * shift + 1, -1)


def weights(win: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The template's least-squares weight at the best shift of each frame ``(F,)`` and that
    shift's index ``(F,)``, for windows ``(F, S, D)`` and a template ``(D,)``."""
    w = win @ t / max(float(t @ t), 1e-12)
    best = np.argmax(w, axis=1)
    return w[np.arange(len(w)), best], best


def template(win: np.ndarray, *, positions: int, keep: float, iterations: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """The region's template and the frames it was estimated from.

    Parameters
    ----------
    win : (F, S, D) float
        The region's windows (:func:`windows`) in the frames with a face; ``S`` odd, the
        middle one unshifted.
    positions : int
        ``K``, the positions along the contour (the windows' first axis before flattening).
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
    middle = win[:, win.shape[1] // 2]
    across = middle.reshape(len(middle), positions, -1).mean(axis=1)  # the profile across the contour
    energy = np.einsum("fd,fd->f", across, across)
    seen = energy >= np.median(energy)
    t = np.median(middle[seen], axis=0)
    for _ in range(iterations):
        w, best = weights(win, t)
        level = float(np.median(w[seen]))
        now = w > keep * level if level > 1e-9 else np.zeros(len(w), bool)
        if now.sum() < MIN_FRAMES:
            break
        seen, t = now, np.median(win[now, best[now]], axis=0)
    return t, seen


def visibility(win: np.ndarray, t: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """The visibility of the module doc for each frame ``(F,)``: the template's weight at the
    best shift relative to the ``seen`` frames (:func:`relative`)."""
    return relative(weights(win, t)[0], seen)


def relative(measure: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """A per-frame structure measure ``(F,)`` over its median in the ``seen`` frames (all 0
    where that median is not positive: the clip never shows the structure)."""
    level = float(np.median(measure[seen])) if seen.any() else 0.0
    return measure / level if level > 1e-9 else np.zeros(len(measure))


def local_visibility(win: np.ndarray, shape: np.ndarray, seen: np.ndarray, frames: np.ndarray, *, neighbours: int) -> np.ndarray:
    """A second opinion for ``frames``: each frame's strip against a template of the ``seen``
    frames whose face has the nearest shape (head pose and expression, :func:`profiles.shape`),
    so that a pose or an expression far from the clip's typical one is judged against frames
    like it, not against the typical face.

    Parameters
    ----------
    win : (F, S, D) windows; shape : (F, P) the frames' shapes; seen : (F,) bool.
    frames : indices of the frames to judge.
    neighbours : seen frames per template (the nearest in shape among at most :data:`POOL` seen
        frames spread over the clip, the frame itself excluded).

    Returns
    -------
    (len(frames),) the template's weight at the best shift over its median weight in those
    neighbours (0 where there are too few seen frames).
    """
    pool = np.flatnonzero(seen)
    pool = pool[np.unique(np.linspace(0, len(pool) - 1, min(len(pool), POOL)).round().astype(int))] if len(pool) else pool
    out = np.zeros(len(frames))
    if len(pool) < MIN_FRAMES:
        return out
    for i, f in enumerate(frames):
        candidates = pool[pool != f]
        near = candidates[np.argsort(np.sum((shape[candidates] - shape[f]) ** 2, axis=1))[:neighbours]]
        _, best = weights(win[near], np.median(win[near, win.shape[1] // 2], axis=0))
        t = np.median(win[near, best], axis=0)
        level = float(np.median(weights(win[near], t)[0]))
        out[i] = weights(win[f : f + 1], t)[0][0] / level if level > 1e-9 else 0.0
    return out


def median_filter(values: np.ndarray, width: int) -> np.ndarray:
    """Running median over ``width`` (odd) consecutive values ``(F,)``, the values mirrored about
    the ends (a one-frame blip in the first frame is removed like any other)."""
    if width <= 1 or len(values) == 0:
        return np.asarray(values, np.float64)
    half = width // 2
    padded = np.pad(np.asarray(values, np.float64), half, mode="reflect")
    return np.median(np.lib.stride_tricks.sliding_window_view(padded, width), axis=1)
