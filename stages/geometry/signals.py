"""Expression signals of a face geometry, normalized by its own eye distance.

Used to judge whether a target follows a performer (benchmarks, the run report): each signal is
measured in the face's own eye-line frame, so head roll and face size cancel out.

- **eye line**: from the outer corner of one eye to the other (layout points ``eye_l_6``,
  ``eye_r_6``); its length is the *eye distance* ``e``, its unit normal ``n`` points down the face.
- **mouth opening**: mean position of the lower inner lip (``mouth_inner_6..9``) minus that of the
  upper inner lip (``mouth_inner_1..4``), along ``n``, over ``e``.
- **mouth width**: distance between the outer mouth corners (``mouth_outer_0``, ``mouth_outer_8``)
  over ``e``.
- **brow raise**: mean distance of the brow points (``brow_l_*``, ``brow_r_*``) above the eye line,
  along ``-n``, over ``e``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

EYE_OUTER = ("eye_l_6", "eye_r_6")
UPPER_INNER_LIP = ("mouth_inner_1", "mouth_inner_2", "mouth_inner_3", "mouth_inner_4")
LOWER_INNER_LIP = ("mouth_inner_6", "mouth_inner_7", "mouth_inner_8", "mouth_inner_9")
MOUTH_CORNERS = ("mouth_outer_0", "mouth_outer_8")
BROWS = tuple(f"brow_{side}_{k}" for side in "lr" for k in range(8))
SIGNALS = ("mouth_open", "mouth_width", "brow_raise")


def named_points(names: Sequence[str], wanted: Sequence[str]) -> list[int]:
    """Columns of the ``wanted`` layout points among ``names``, in ``wanted`` order; ValueError
    naming the missing ones."""
    where = {str(n): i for i, n in enumerate(names)}
    missing = [w for w in wanted if w not in where]
    if missing:
        raise ValueError(f"expression signals need layout points {missing}, which the geometry does not have")
    return [where[w] for w in wanted]


def eye_line_frame(xy: np.ndarray, names: Sequence[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The eye-line frame of each geometry ``(T, N, 2)`` px: the midpoint of the outer eye corners
    ``(T, 2)`` px, the unit vector along the eye line ``(T, 2)`` and its normal pointing down the
    face ``(T, 2)`` (x right, y down: ``(x, y) -> (-y, x)``), and the eye distance ``(T,)`` px."""
    left, right = (xy[:, c] for c in named_points(names, EYE_OUTER))
    axis = right - left
    eye = np.linalg.norm(axis, axis=-1)
    along = axis / eye[:, None]
    down = np.stack([-along[:, 1], along[:, 0]], axis=-1)
    return (left + right) / 2, along, down, eye


def expression_signals(xy: np.ndarray, names: Sequence[str]) -> dict[str, np.ndarray]:
    """Mouth opening, mouth width and brow raise of each frame, in eye distances.

    Parameters
    ----------
    xy : (T, N, 2) float
        Layout points per frame, px.
    names : (N,) str
        Their layout names (zhang134).

    Returns
    -------
    dict
        ``mouth_open``, ``mouth_width``, ``brow_raise``, ``eye_distance_px``: each ``(T,)``.
    """
    xy = np.asarray(xy, np.float64)
    centre, _, down, eye = eye_line_frame(xy, names)
    upper = xy[:, named_points(names, UPPER_INNER_LIP)].mean(axis=1)
    lower = xy[:, named_points(names, LOWER_INNER_LIP)].mean(axis=1)
    corners = xy[:, named_points(names, MOUTH_CORNERS)]
    brows = xy[:, named_points(names, BROWS)].mean(axis=1)
    return {
        "mouth_open": np.sum((lower - upper) * down, axis=-1) / eye,
        "mouth_width": np.linalg.norm(corners[:, 1] - corners[:, 0], axis=-1) / eye,
        "brow_raise": -np.sum((brows - centre) * down, axis=-1) / eye,
        "eye_distance_px": eye,
    }


def follow(performer: np.ndarray, target: np.ndarray, valid: np.ndarray | None = None) -> tuple[float, float]:
    """How well a target signal follows a performer signal: Pearson correlation and amplitude
    ratio (standard deviation of the target's over the performer's), over ``valid`` frames.

    Returns ``(nan, nan)`` when fewer than 3 frames are valid or the performer's signal is constant.
    """
    performer, target = np.asarray(performer, np.float64), np.asarray(target, np.float64)
    keep = np.isfinite(performer) & np.isfinite(target)
    if valid is not None:
        keep &= np.asarray(valid, bool)
    p, t = performer[keep], target[keep]
    if p.size < 3 or p.std() == 0:
        return float("nan"), float("nan")
    r = float(np.corrcoef(p, t)[0, 1]) if t.std() > 0 else 0.0
    return r, float(t.std() / p.std())
