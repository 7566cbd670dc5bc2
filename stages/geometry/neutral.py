"""The performer's neutral geometry estimated from a whole clip, region by region.

Expression mapping carries displacements from the performer's neutral face (Sec. 11). Real
footage often has no neutral moment: a clip cut into a dialogue starts mid-expression, a
performer cries with the eyes squeezed shut for seconds. A single reference frame then makes
every displacement relative to that expression (the target keeps its eyes open whenever the
performer's are shut, for the whole clip). So the neutral is estimated per *expression region*
— each eye, the brows, the mouth, the rest — from the frames in which that region is at rest,
judged by the face landmarker's blendshape scores (a learned reading of each region's activity)
and by the geometry itself, never from a frame where the region is occluded or the head is
turned far from the head frame:

    N_R = median over t in F_R of X'_t[R]       (per point of region R, in the head frame)

with ``X'_t`` the frame's points taken back into the head frame (:mod:`stages.geometry.rigid3d`)
and ``F_R`` the ``k`` eligible frames of lowest activity of region R (``k`` = a fraction of the
eligible frames, at least :data:`MIN_FRAMES`). Eligible for an eye: its lid gap at least
:data:`OPEN_FRACTION` of the clip's open level (the 90th percentile of its gap), so a blink or a
squint never enters; for the mouth, frames with sealed lips are preferred when there are enough.
The estimate is a composite: the eyes may come from other frames than the mouth.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from stages.geometry.states import SEALED_GAP, state_signals

#: Expression regions: the name prefixes of their zhang134 points and the MediaPipe blendshapes
#: whose sum is the region's activity. MediaPipe names sides from the subject: its ``Left`` is
#: the image-right eye, the layout's ``eye_r``.
REGIONS = {
    "eye_l": (("eye_l_", "crease_l_", "under_eye_l"), ("eyeBlinkRight", "eyeSquintRight", "eyeWideRight", "cheekSquintRight")),
    "eye_r": (("eye_r_", "crease_r_", "under_eye_r"), ("eyeBlinkLeft", "eyeSquintLeft", "eyeWideLeft", "cheekSquintLeft")),
    "brows": (
        ("brow_", "forehead_", "glabella", "hairline_"),
        ("browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight"),
    ),
    "mouth": (
        (
            "mouth_",
            "teeth_",
            "chin",
            "nasolabial_",
            "cheek_",
            "lipfold_",
            "nose_ala",
            "nose_nostril",
            "contour_3",
            "contour_4",
            "contour_5",
            "contour_6",
            "contour_7",
            "contour_8",
            "contour_9",
            "contour_10",
            "contour_11",
            "contour_12",
            "contour_13",
        ),
        (
            "jawOpen",
            "jawForward",
            "jawLeft",
            "jawRight",
            "mouthFunnel",
            "mouthPucker",
            "mouthLeft",
            "mouthRight",
            "mouthSmileLeft",
            "mouthSmileRight",
            "mouthFrownLeft",
            "mouthFrownRight",
            "mouthDimpleLeft",
            "mouthDimpleRight",
            "mouthStretchLeft",
            "mouthStretchRight",
            "mouthRollLower",
            "mouthRollUpper",
            "mouthShrugLower",
            "mouthShrugUpper",
            "mouthPressLeft",
            "mouthPressRight",
            "mouthLowerDownLeft",
            "mouthLowerDownRight",
            "mouthUpperUpLeft",
            "mouthUpperUpRight",
            "cheekPuff",
            "noseSneerLeft",
            "noseSneerRight",
        ),
    ),
}
REST = "rest"  # the points of no region (the skull's: nose bridge, temples, upper contour): all eligible frames
MIN_FRAMES = 5
FRACTION = 0.15  # of the eligible frames, the least active ones form a region's neutral
MAX_FRAMES = 60
OPEN_FRACTION = 0.7  # an eye's neutral frames have at least this fraction of its open level


def point_regions(names: Sequence[str]) -> dict[str, np.ndarray]:
    """``{region: (N,) bool}`` for :data:`REGIONS` and :data:`REST`: which points each region
    holds (by zhang134 name prefix; a point in no region is in ``rest``)."""
    names = [str(n) for n in names]
    out = {region: np.array([n.startswith(prefixes) for n in names]) for region, (prefixes, _) in REGIONS.items()}
    out[REST] = ~np.any(list(out.values()), axis=0)
    return out


def region_activity(blendshapes: np.ndarray, blendshape_names: Sequence[str]) -> dict[str, np.ndarray]:
    """``{region: (T,)}``: the sum of each region's blendshape scores per frame."""
    where = {str(n): i for i, n in enumerate(blendshape_names)}
    scores = np.asarray(blendshapes, np.float64)
    return {region: scores[:, [where[b] for b in shapes if b in where]].sum(axis=1) for region, (_, shapes) in REGIONS.items()}


@dataclass(frozen=True)
class NeutralEstimate:
    """The estimated neutral and how it was made.

    ``neutral (N, 2)`` px in the head frame; ``frames``: per region (and ``rest``) the frames its
    median was taken over; ``eye_open_known``: per eye, False when no frame had that eye open
    (its neutral is then the clip's median and its lid gap is no open level); ``nearest_frame``:
    the eligible frame whose geometry is closest to the neutral (RMS over the points).
    """

    neutral: np.ndarray
    frames: Mapping[str, np.ndarray]
    eye_open_known: Mapping[str, bool] = field(default_factory=dict)
    nearest_frame: int = -1

    @property
    def n_frames(self) -> int:
        """How many distinct frames contributed."""
        return int(np.unique(np.concatenate([np.asarray(f) for f in self.frames.values()])).size)


def estimate_neutral(
    aligned: np.ndarray,
    names: Sequence[str],
    eligible: np.ndarray,
    blendshapes: np.ndarray,
    blendshape_names: Sequence[str],
    *,
    occluded: Mapping[str, np.ndarray] | None = None,
) -> NeutralEstimate:
    """The neutral geometry of a clip (module docstring).

    Parameters
    ----------
    aligned : (T, N, 2) float
        Every frame's points taken back into the head frame, px.
    names : (N,) str
        zhang134 point names.
    eligible : (T,) bool
        Frames that may contribute at all (a face, the head not turned far from the head frame).
    blendshapes : (T, B) float
        The landmarker's blendshape scores; ``blendshape_names (B,)``.
    occluded : {region: (T,) bool}, optional
        Frames where a region is hidden (an occluder's frames never enter that region's neutral).
        Keys ``mouth``, ``eye_l``, ``eye_r``, ``brow_l``/``brow_r`` (both count for ``brows``).

    Returns
    -------
    NeutralEstimate

    Raises
    ------
    ValueError
        No eligible frame.
    """
    aligned = np.asarray(aligned, np.float64)
    eligible = np.asarray(eligible, bool)
    if not eligible.any():
        raise ValueError("no frame with a face to estimate the neutral from")
    occluded = dict(occluded or {})
    if "brow_l" in occluded or "brow_r" in occluded:
        occluded["brows"] = np.any([occluded[k] for k in ("brow_l", "brow_r") if k in occluded], axis=0)
    members = point_regions(names)
    activity = region_activity(blendshapes, blendshape_names)
    signals = state_signals(np.where(np.isfinite(aligned), aligned, 0.0), names)
    neutral = np.full(aligned.shape[1:], np.nan)
    frames: dict[str, np.ndarray] = {}
    known: dict[str, bool] = {}
    for region, points in members.items():
        ok = eligible & ~np.asarray(occluded.get(region, np.zeros(len(eligible), bool)), bool)
        if not ok.any():
            ok = eligible
        if region == REST:
            chosen = np.flatnonzero(ok)
        else:
            preferred = ok.copy()
            if region.startswith("eye_"):
                gap = signals[f"eye_open_{region[-1]}"]
                level = np.percentile(gap[ok], 90)
                preferred &= gap >= OPEN_FRACTION * level
                known[region] = bool(level > 0.03 and preferred.sum() >= min(MIN_FRAMES, ok.sum()))
            elif region == "mouth":
                sealed = preferred & (signals["mouth_open"] < SEALED_GAP)
                if sealed.sum() >= MIN_FRAMES:
                    preferred = sealed
            if preferred.sum() < MIN_FRAMES:
                preferred = ok
            chosen = least_active(activity[region], preferred)
        frames[region] = chosen
        neutral[points] = np.nanmedian(aligned[chosen][:, points], axis=0)
    rms = np.sqrt(np.nanmean(np.sum((aligned - neutral[None]) ** 2, axis=-1), axis=1))
    nearest = int(np.flatnonzero(eligible)[np.nanargmin(rms[eligible])])
    return NeutralEstimate(neutral, frames, known, nearest)


def least_active(activity: np.ndarray, allowed: np.ndarray) -> np.ndarray:
    """The frames ``(k,)`` of lowest ``activity (T,)`` among ``allowed (T,)``, ``k`` =
    :data:`FRACTION` of the allowed frames, within [:data:`MIN_FRAMES`, :data:`MAX_FRAMES`] (all of
    them when fewer), in frame order."""
    candidates = np.flatnonzero(allowed)
    k = int(np.clip(round(FRACTION * candidates.size), MIN_FRAMES, MAX_FRAMES))
    order = np.argsort(activity[candidates], kind="stable")[:k]
    return np.sort(candidates[order])
