"""Expression deformations of the fitted mesh: mouth opening, brow raise, smile, and the states a
viewer judges a performance by: each eye shut, eyes wide, brow furrow, pucker, lip press.

Each expression ``k`` is a parameter ``p_k`` in [0, 1] and a displacement field ``B_k`` ``(V, 3)``
mm per unit parameter, applied in the head frame before the pose:
``X(p) = X_neutral + sum_k p_k B_k`` (linear, so the truth is exact for any mix).
Weights are smooth functions of each vertex's photo position (``smoothstep`` falloffs), with
lengths in units of the outer-eye-corner distance ``D``:

- ``mouth_open``: lower lip, chin and jaw move down by up to :data:`MOUTH_OPEN_MAX` ``D`` (the lower
  lip's centre; the lip corners stay), slightly backwards (a jaw rotation's direction); the
  weight rises from 0 on the line through the mouth corners to 1 within a band (0.6 of the half
  mouth width at the centre, wider towards the ears), fading below the chin (the neck stretches)
  and towards the ears. Lips are told apart by their contours
  (upper lip 0, lower lip by a profile across the mouth).
- ``brow_raise``: brows and forehead up by :data:`BROW_RAISE_MAX` ``D``, from 0 at the upper
  eyelids to 1 at the brows, fading into the hair and beyond the temples.
- ``smile``: mouth corners up and out by :data:`SMILE_CORNER_MAX` ``D`` (Gaussian falloff), cheeks
  up by :data:`SMILE_CHEEK_MAX` ``D``.

The state expressions (:data:`STATE_EXPRESSIONS`, :func:`state_basis`; the default clips keep the
three above, so their truth files stay the same):

- ``blink_l`` / ``blink_r`` (the image-left / image-right eye): the upper lid comes down onto the
  lower one. Inside the eye opening a vertex moves to the lower lid below it; above the opening
  the lid's skin follows, from 1 at the lid margin to 0 at the brow (the skin stretches over the
  eye as a lid does); the lower lid stays. ``0.5`` is a squint, ``1`` shut.
- ``eye_wide``: both upper lids and their skin up by :data:`EYE_WIDE_MAX` of each eye's opening.
- ``brow_furrow``: the inner brow ends towards the face's midline by :data:`FURROW_IN_MAX` ``D``
  and down by :data:`FURROW_DOWN_MAX` ``D`` (Gaussian falloff about each inner end).
- ``pucker``: the mouth narrows towards its centre by :data:`PUCKER_MAX` of each point's
  distance to it (Gaussian falloff); with ``mouth_open`` an "O".
- ``lip_press``: each lip's red part thinned by :data:`LIP_PRESS_MAX` towards the inner lip line.
"""

from __future__ import annotations

import numpy as np
from matplotlib.path import Path as PolygonPath

from .landmarks import (
    BROWS,
    CHEEKS,
    CHIN,
    FACE_OVAL,
    FOREHEAD,
    LIPS_INNER_LOWER,
    LIPS_INNER_UPPER,
    LIPS_OUTER_LOWER,
    LIPS_OUTER_UPPER,
    MOUTH_CORNERS,
    N_LANDMARKS,
    UPPER_LIDS,
)
from .mesh import MOUTH_OPEN_MAX, RealFaceMesh

EXPRESSIONS = ("mouth_open", "brow_raise", "smile")
STATE_EXPRESSIONS = EXPRESSIONS + ("blink_l", "blink_r", "eye_wide", "brow_furrow", "pucker", "lip_press")
EYE_WIDE_MAX = 0.35
FURROW_IN_MAX = 0.06
FURROW_DOWN_MAX = 0.05
PUCKER_MAX = 0.3
LIP_PRESS_MAX = 0.6
# MediaPipe mesh indices of each eye's lids (outer corner to inner), irises, and the inner brow ends:
# the image-left eye is the subject's right
EYE_LIDS = {
    "l": ((33, 246, 161, 160, 159, 158, 157, 173, 133), (33, 7, 163, 144, 145, 153, 154, 155, 133), range(468, 473)),
    "r": ((263, 466, 388, 387, 386, 385, 384, 398, 362), (263, 249, 390, 373, 374, 380, 381, 382, 362), range(473, 478)),
}
INNER_BROW_ENDS = ((55, 107), (285, 336))
BROW_RAISE_MAX = 0.12
SMILE_CORNER_MAX = 0.13
SMILE_CHEEK_MAX = 0.07
JAW_BACK = 0.15  # backward (z) motion of the jaw per unit of downward motion


def smoothstep(lo: float, hi: float, x: np.ndarray) -> np.ndarray:
    """0 below ``lo``, 1 above ``hi``, ``3u^2 - 2u^3`` between (``lo > hi`` gives the falling step)."""
    with np.errstate(divide="ignore", invalid="ignore"):  # lo == hi: a step (NaN where x == lo, taken as 0)
        u = np.nan_to_num(np.clip((np.asarray(x, dtype=np.float64) - lo) / (hi - lo), 0.0, 1.0))
    return u * u * (3.0 - 2.0 * u)


def _lip_sides(px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boolean ``(V,)`` masks of the upper and the lower lip (inside each lip's outline or on its
    contours; the mouth corners count as upper lip, so they stay when the mouth opens)."""
    lm = px[:N_LANDMARKS]
    upper = PolygonPath(lm[list(LIPS_OUTER_UPPER + LIPS_INNER_UPPER[::-1])]).contains_points(px)
    lower = PolygonPath(lm[list(LIPS_OUTER_LOWER + LIPS_INNER_LOWER[::-1])]).contains_points(px)
    upper[list(LIPS_OUTER_UPPER + LIPS_INNER_UPPER)] = True
    lower[list(LIPS_OUTER_LOWER + LIPS_INNER_LOWER)] = True
    return upper, lower & ~upper


def _mouth_open(px: np.ndarray, D: float) -> np.ndarray:
    """``(V,)`` downward weight of the jaw."""
    lm = px[:N_LANDMARKS]
    left, right = lm[MOUTH_CORNERS[0]], lm[MOUTH_CORNERS[1]]
    centre = (left + right) / 2.0
    half = np.linalg.norm(right - left) / 2.0
    slope = (right[1] - left[1]) / (right[0] - left[0])
    below = px[:, 1] - (left[1] + slope * (px[:, 0] - left[0]))
    across = np.abs(px[:, 0] - centre[0])
    band = 0.6 * half + np.maximum(across - half, 0.0)  # wider towards the ears: no step at the jaw line
    jaw = smoothstep(0.0, band, below)
    jaw *= smoothstep(lm[CHIN, 1] + 0.6 * D, lm[CHIN, 1] + 0.1 * D, px[:, 1])
    jaw *= smoothstep(1.1 * D, 0.4 * D, across)
    upper, lower = _lip_sides(px)
    profile = smoothstep(1.0 * half, 0.3 * half, across)
    return np.where(upper, 0.0, np.where(lower, profile, jaw))


def _brow_raise(px: np.ndarray, D: float) -> np.ndarray:
    """``(V,)`` upward weight of brows and forehead."""
    lm = px[:N_LANDMARKS]
    lid = lm[list(UPPER_LIDS), 1].min()  # the higher lid: neither moves
    brow = lm[list(BROWS), 1].mean()
    centre_x = lm[list(FACE_OVAL), 0].mean()
    w = smoothstep(lid, brow, px[:, 1])
    w *= smoothstep(lm[FOREHEAD, 1] - 0.7 * D, lm[FOREHEAD, 1], px[:, 1])
    w *= smoothstep(1.0 * D, 0.7 * D, np.abs(px[:, 0] - centre_x))
    return w


def _gaussian(px: np.ndarray, centre: np.ndarray, sigma: float) -> np.ndarray:
    return np.exp(-np.sum((px - centre) ** 2, axis=1) / (2.0 * sigma * sigma))


def expression_basis(mesh: RealFaceMesh) -> np.ndarray:
    """Displacement fields ``(3, V, 3)`` mm per unit parameter, in :data:`EXPRESSIONS` order.

    The mouth cavity's vertices (the upper teeth) stay with the upper jaw when the mouth opens
    or the brows rise, and follow the smile's field (so the teeth stay behind the lips).
    """
    px, D, mm = mesh.source_px, mesh.eye_px, mesh.mm_per_px
    basis = np.zeros((len(EXPRESSIONS), len(px), 3))
    skin = np.arange(len(px)) < len(px) - mesh.n_cavity
    down = MOUTH_OPEN_MAX * D * mm * _mouth_open(px, D) * skin
    basis[0, :, 1] = down
    basis[0, :, 2] = JAW_BACK * down
    basis[1, :, 1] = -BROW_RAISE_MAX * D * mm * _brow_raise(px, D) * skin
    lm = px[:N_LANDMARKS]
    centre_x = lm[list(MOUTH_CORNERS), 0].mean()
    for corner, cheek in zip(MOUTH_CORNERS, CHEEKS):
        side = np.sign(lm[corner, 0] - centre_x)
        g = _gaussian(px, lm[corner], 0.35 * D)
        basis[2, :, 0] += side * SMILE_CORNER_MAX * 0.6 * D * mm * g
        basis[2, :, 1] -= SMILE_CORNER_MAX * 0.8 * D * mm * g
        basis[2, :, 1] -= SMILE_CHEEK_MAX * D * mm * _gaussian(px, lm[cheek], 0.4 * D)
    return basis


def _lid(px: np.ndarray, contour: tuple[int, ...], x: np.ndarray) -> np.ndarray:
    """The lid line through landmarks ``contour`` evaluated at ``x`` (linear, held past the corners)."""
    points = px[list(contour)]
    order = np.argsort(points[:, 0])
    return np.interp(x, points[order, 0], points[order, 1])


def _eye_fields(px: np.ndarray, side: str) -> tuple[np.ndarray, np.ndarray]:
    """``(V,)`` px each: the downward move of a blink of eye ``side`` and the upward move of a
    wide eye (module docstring)."""
    upper_ids, lower_ids, iris = EYE_LIDS[side]
    lm = px[:N_LANDMARKS]
    x, y = px[:, 0], px[:, 1]
    upper, lower = _lid(lm, upper_ids, x), _lid(lm, lower_ids, x)
    corners = lm[[upper_ids[0], upper_ids[-1]]]
    across = (x >= corners[:, 0].min()) & (x <= corners[:, 0].max())
    gap = np.where(across, np.maximum(lower - upper, 0.0), 0.0)
    span = np.ptp(corners[:, 0])
    near = [b for b in BROWS if abs(lm[b, 0] - corners[:, 0].mean()) < 0.7 * span]
    brow = lm[near, 1].max()  # the brow's lowest point over this eye: the lid's skin ends there
    opening = across & (y > upper - 1e-6) & (y < lower - 1e-6)
    opening[list(iris)] = True
    skin = across & (y <= upper) & (y > brow)
    lid_weight = np.where(skin, smoothstep(brow, upper, y), 0.0)
    down = np.where(opening, np.maximum(lower - y, 0.0), gap * lid_weight)
    up = EYE_WIDE_MAX * gap * np.where(opening, smoothstep(lower, upper, y), lid_weight)
    return down, up


def state_basis(mesh: RealFaceMesh) -> np.ndarray:
    """Displacement fields ``(9, V, 3)`` mm per unit parameter, in :data:`STATE_EXPRESSIONS`
    order: :func:`expression_basis`'s three, then the states (module docstring)."""
    px, D, mm = mesh.source_px, mesh.eye_px, mesh.mm_per_px
    skin = (np.arange(len(px)) < len(px) - mesh.n_cavity)[:, None]
    lm = px[:N_LANDMARKS]
    fields = np.zeros((6, len(px), 3))
    wide = np.zeros(len(px))
    for k, side in enumerate("lr"):
        down, up = _eye_fields(px, side)
        fields[k, :, 1] = down * mm
        wide += up
    fields[2, :, 1] = -wide * mm
    centre_x = lm[list(FACE_OVAL), 0].mean()
    for ends in INNER_BROW_ENDS:
        end = lm[list(ends)].mean(axis=0)
        g = _gaussian(px, end, 0.25 * D)
        fields[3, :, 0] += -np.sign(end[0] - centre_x) * FURROW_IN_MAX * D * mm * g
        fields[3, :, 1] += FURROW_DOWN_MAX * D * mm * g
    corners = lm[list(MOUTH_CORNERS)]
    mouth_centre = corners.mean(axis=0)
    half = np.linalg.norm(corners[1] - corners[0]) / 2.0
    g = _gaussian(px, mouth_centre, 0.8 * half)
    fields[4, :, 0] = -PUCKER_MAX * (px[:, 0] - mouth_centre[0]) * mm * g
    fields[4, :, 2] = -0.15 * half * mm * g  # the lips come forward
    upper, lower = _lip_sides(px)
    inner_up, inner_low = _lid(lm, LIPS_INNER_UPPER, px[:, 0]), _lid(lm, LIPS_INNER_LOWER, px[:, 0])
    press = np.where(upper, inner_up - px[:, 1], np.where(lower, inner_low - px[:, 1], 0.0))
    fields[5, :, 1] = LIP_PRESS_MAX * press * mm
    return np.concatenate([expression_basis(mesh), fields * skin[None]])


def deform(mesh: RealFaceMesh, basis: np.ndarray, params: np.ndarray) -> np.ndarray:
    """Head-frame vertices ``(V, 3)`` mm of expression ``params`` ``(K,)`` in [0, 1], one per
    field of ``basis`` ``(K, V, 3)`` (:func:`expression_basis` or :func:`state_basis`)."""
    params = np.asarray(params, dtype=np.float64)
    if params.shape != (len(basis),) or np.any(params < 0) or np.any(params > 1):
        raise ValueError(f"params: expected ({len(basis)},) values in [0, 1], got {params!r}")
    return mesh.vertices + np.tensordot(params, basis, axes=1)
