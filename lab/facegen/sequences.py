"""Expression sets and clip trajectories: captured expressions, example selection (Sec. 14),
performer head motion and expression curves, and the 2D similarity of eq. 8-9."""

from __future__ import annotations

import numpy as np

from stages.eigen.facegen.face import CONTROLS

CONTROL_INDEX = {n: i for i, n in enumerate(CONTROLS)}

# expression "recipes" the captured sets are drawn around: (control, low, high). They reach what
# real performers do: mouth openings to about half the outer-eye-corner distance (jaw_drop 1),
# broad and open smiles, brows fully raised and lowered.
RECIPES: tuple[tuple[tuple[str, float, float], ...], ...] = (
    (("smile", 0.6, 1.0),),
    (("jaw_drop", 0.9, 1.0),),
    (("smile", 0.5, 1.0), ("jaw_drop", 0.3, 0.8)),
    (("inner_brow_raise", 0.6, 1.0), ("outer_brow_raise", 0.5, 1.0)),
    (("inner_brow_raise", 0.6, 1.0), ("outer_brow_raise", 0.5, 1.0), ("jaw_drop", 0.6, 1.0)),
    (("brow_lower", 0.6, 1.0), ("squint", 0.2, 0.6)),
    (("brow_lower", 0.5, 1.0), ("lip_corner_depress", 0.4, 1.0), ("chin_raise", 0.2, 0.7)),
    (("lip_pucker", 0.5, 1.0),),
    (("lip_stretch", 0.5, 1.0), ("brow_lower", 0.0, 0.5)),
    (("upper_lip_raise", 0.5, 1.0), ("brow_lower", 0.2, 0.6)),
    (("lip_corner_depress", 0.5, 1.0), ("inner_brow_raise", 0.3, 0.8)),
    (("squint", 0.5, 1.0), ("smile", 0.3, 0.7)),
    (("lid_close", 0.7, 1.0), ("brow_lower", 0.7, 1.0), ("lip_stretch", 0.3, 0.7)),  # wince: big enough to be an example
    (("chin_raise", 0.5, 1.0), ("lip_pucker", 0.0, 0.4)),
    (("jaw_drop", 0.2, 0.6), ("lip_stretch", 0.0, 0.3)),
    (("smile", 0.8, 1.0), ("upper_lip_raise", 0.4, 0.9), ("jaw_drop", 0.2, 0.5)),
)

# standard image (Sec. 5.2: mouth open so the teeth texture exists) and teeth examples (Sec. 8):
# small, speech-sized, wide (inner lips half the outer-eye-corner distance apart) and a broad open smile
STANDARD: dict[str, float] = {"jaw_drop": 0.55, "upper_lip_raise": 0.35}
TEETH: tuple[dict[str, float], ...] = (
    {"jaw_drop": 0.4, "smile": 0.5},
    {"jaw_drop": 0.75, "upper_lip_raise": 0.3},
    {"jaw_drop": 1.0, "lip_stretch": 0.3},
    {"jaw_drop": 0.65, "smile": 1.0, "upper_lip_raise": 0.5},
)

# The combinatorial set: examples that each move one facial region, held-out expressions that
# combine regions (the case where per-subregion synthesis beats one global convex combination).
REGION_MOVES: dict[str, dict[str, float]] = {
    "brows_raised": {"inner_brow_raise": 1.0, "outer_brow_raise": 1.0},
    "brows_lowered": {"brow_lower": 1.0},
    "lids_closed": {"lid_close": 1.0},
    "squint": {"squint": 1.0},
    "smile": {"smile": 1.0},
    "mouth_open": {"jaw_drop": 1.0},
    "pucker": {"lip_pucker": 1.0},
    "corners_down": {"lip_corner_depress": 1.0},
    "upper_lip_raised": {"upper_lip_raise": 1.0},
    "lips_stretched": {"lip_stretch": 1.0},
    "chin_raised": {"chin_raise": 1.0},
}
COMBO_HELDOUT: tuple[tuple[str, ...], ...] = (
    ("brows_raised", "smile"),
    ("brows_raised", "mouth_open"),
    ("brows_raised", "pucker"),
    ("brows_raised", "lids_closed"),
    ("brows_lowered", "smile"),
    ("brows_lowered", "mouth_open"),
    ("brows_lowered", "corners_down"),
    ("brows_lowered", "squint", "pucker"),
    ("lids_closed", "smile"),
    ("lids_closed", "mouth_open"),
    ("squint", "corners_down"),
    ("brows_raised", "squint", "lips_stretched"),
)


def controls_of(**values: float) -> np.ndarray:
    """A ``(C,)`` controls vector from keyword values (unnamed controls are 0)."""
    c = np.zeros(len(CONTROLS))
    for name, v in values.items():
        c[CONTROL_INDEX[name]] = v
    return c


def captured_controls(rng: np.random.Generator, count: int, *, jaw_max: float = 1.0) -> np.ndarray:
    """``(count, C)`` expressions "of whatever the subject can make" (Sec. 14): each follows a
    recipe (cycled, so all are covered) with random strengths plus a little of other controls.
    ``jaw_max`` scales every ``jaw_drop`` (the same draws): a subject who never opens wide."""
    out = np.zeros((count, len(CONTROLS)))
    for k in range(count):
        for name, lo, hi in RECIPES[k % len(RECIPES)]:
            out[k, CONTROL_INDEX[name]] = rng.uniform(lo, hi)
        extra = rng.integers(len(CONTROLS))
        out[k, extra] = max(out[k, extra], rng.uniform(0.0, 0.3))
    out[:, CONTROL_INDEX["jaw_drop"]] *= jaw_max
    return out


def combo_controls() -> tuple[np.ndarray, list[str], int]:
    """The combinatorial set: controls ``(K, C)``, names (moves joined by ``+``) and the number of
    leading rows that are examples (one region each, :data:`REGION_MOVES`); the rest are the
    held-out combinations of :data:`COMBO_HELDOUT`."""
    names = list(REGION_MOVES) + ["+".join(moves) for moves in COMBO_HELDOUT]
    rows = [controls_of(**REGION_MOVES[n]) for n in REGION_MOVES]
    rows += [sum(controls_of(**REGION_MOVES[m]) for m in moves) for moves in COMBO_HELDOUT]
    return np.clip(np.stack(rows), 0.0, 1.0), names, len(REGION_MOVES)


def farthest_point_selection(vectors: np.ndarray, count: int) -> np.ndarray:
    """Pick ``count`` rows of ``vectors`` ``(K, D)`` that differ from each other and cover the set.

    Greedy farthest-point order: start from the row farthest from the origin (the neutral
    geometry when ``vectors`` are displacements), then repeatedly add the row farthest from
    those chosen — the paper's criterion (Sec. 14) made explicit. Returns sorted indices.
    """
    chosen = [int(np.argmax(np.linalg.norm(vectors, axis=1)))]
    dist = np.linalg.norm(vectors - vectors[chosen[0]], axis=1)
    while len(chosen) < count:
        k = int(np.argmax(dist))
        chosen.append(k)
        dist = np.minimum(dist, np.linalg.norm(vectors - vectors[k], axis=1))
    return np.sort(np.array(chosen))


def similarity_eq9(neutral: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """Least-squares 2D similarity (a, b, tx, ty) mapping ``neutral`` onto ``frame`` (eq. 8-9).

    Parameters
    ----------
    neutral, frame
        ``(n, 2)`` px corresponding points (the rigid points of the layout).

    Returns
    -------
    numpy.ndarray
        ``(4,)``: ``T(x, y) = [[a, -b], [b, a]] @ (x, y) + (tx, ty)`` minimizing eq. 9 (closed form
        after removing the centroids).
    """
    mu_s, mu_d = neutral.mean(axis=0), frame.mean(axis=0)
    s, d = neutral - mu_s, frame - mu_d
    den = float(np.sum(s * s))
    a = float(np.sum(s[:, 0] * d[:, 0] + s[:, 1] * d[:, 1])) / den
    b = float(np.sum(s[:, 0] * d[:, 1] - s[:, 1] * d[:, 0])) / den
    tx = mu_d[0] - (a * mu_s[0] - b * mu_s[1])
    ty = mu_d[1] - (b * mu_s[0] + a * mu_s[1])
    return np.array([a, b, tx, ty])


def _smooth_keys(times: np.ndarray, keys: list[tuple[float, np.ndarray]]) -> np.ndarray:
    """Cosine-eased interpolation of keyframes ``(time in [0, 1], controls (C,))`` at ``times``."""
    kt = np.array([k[0] for k in keys])
    kv = np.stack([k[1] for k in keys])
    out = np.zeros((len(times), kv.shape[1]))
    for i, s in enumerate(times):
        j = int(np.clip(np.searchsorted(kt, s, side="right") - 1, 0, len(kt) - 2))
        u = np.clip((s - kt[j]) / (kt[j + 1] - kt[j]), 0.0, 1.0)
        e = 0.5 - 0.5 * np.cos(np.pi * u)
        out[i] = (1 - e) * kv[j] + e * kv[j + 1]
    return out


def clip_trajectory(kind: str, frames: int, fps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Controls ``(T, C)``, head angles ``(T, 3)`` (yaw, pitch, roll; degrees) and head
    translation offsets ``(T, 3)`` mm of a performer clip. Frame 0 is neutral at the reference pose.

    ``calm``: slow expressions, little head motion (within a few degrees). ``live``: head sweeps
    to +-25 deg yaw, +-15 deg pitch, +-10 deg roll with translation, blinks about every 1.3 s,
    speech-like jaw and lip motion, and passing expressions.
    """
    s = np.arange(frames) / max(frames - 1, 1)
    sec = np.arange(frames) / fps
    if kind == "calm":
        keys = [
            (0.0, controls_of()),
            (0.12, controls_of()),
            (0.3, controls_of(smile=0.8, squint=0.2)),
            (0.45, controls_of(inner_brow_raise=0.8, outer_brow_raise=0.7, jaw_drop=0.35)),
            (0.62, controls_of(brow_lower=0.8, lip_corner_depress=0.6, chin_raise=0.3)),
            (0.8, controls_of(lip_pucker=0.7)),
            (0.92, controls_of(smile=0.4)),
            (1.0, controls_of()),
        ]
        controls = _smooth_keys(s, keys)
        angles = np.column_stack(
            [3.0 * np.sin(2 * np.pi * 1.0 * s), 2.0 * np.sin(2 * np.pi * 0.7 * s), 1.5 * np.sin(2 * np.pi * 1.3 * s)]
        )
        shift = np.column_stack(
            [2.0 * np.sin(2 * np.pi * 0.8 * s), 1.5 * np.sin(2 * np.pi * 0.6 * s), 4.0 * np.sin(2 * np.pi * 0.5 * s)]
        )
    elif kind == "live":
        keys = [
            (0.0, controls_of()),
            (0.2, controls_of(smile=0.7)),
            (0.4, controls_of(inner_brow_raise=0.9, outer_brow_raise=0.8)),
            (0.6, controls_of(brow_lower=0.7, lip_stretch=0.4)),
            (0.8, controls_of(smile=0.9, squint=0.3)),
            (1.0, controls_of(lip_corner_depress=0.5)),
        ]
        controls = _smooth_keys(s, keys)
        ramp = np.clip(sec / 0.25, 0.0, 1.0)
        ci = CONTROL_INDEX
        controls[:, ci["jaw_drop"]] += ramp * 0.45 * (0.5 - 0.5 * np.cos(2 * np.pi * 3.2 * sec))
        controls[:, ci["lip_pucker"]] += ramp * 0.45 * np.clip(np.sin(2 * np.pi * 1.7 * sec + 0.5), 0, None) ** 2
        controls[:, ci["lip_stretch"]] += ramp * 0.3 * np.clip(np.sin(2 * np.pi * 2.3 * sec + 2.0), 0, None) ** 2
        controls[:, ci["upper_lip_raise"]] += ramp * 0.3 * np.clip(np.sin(2 * np.pi * 2.9 * sec + 1.0), 0, None) ** 2
        phase = np.mod(sec - 0.45, 1.3)
        controls[:, ci["lid_close"]] = np.clip(1.0 - np.abs(phase - 0.1) / 0.1, 0.0, 1.0) * (sec > 0.3)
        angles = np.column_stack(
            [25.0 * np.sin(2 * np.pi * s), 15.0 * np.sin(2 * np.pi * 1.5 * s), 10.0 * np.sin(2 * np.pi * 2.0 * s)]
        )
        shift = np.column_stack(
            [15.0 * np.sin(2 * np.pi * 1.2 * s), 8.0 * np.sin(2 * np.pi * 0.9 * s), 35.0 * np.sin(2 * np.pi * 0.75 * s)]
        )
    else:
        raise ValueError(f"unknown clip kind {kind!r}")
    return np.clip(controls, 0.0, 1.0), angles, shift
