"""Small synthetic inputs of ``write.report`` with known expression, pose and coefficients.

The target and the performer have a face of the zhang134 layout with a level eye line
(``eye_l_6`` -> ``eye_r_6``); the lower inner lip moves straight down by a known number of eye
distances, so the mouth-opening signal is known exactly.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from stages.geometry.signals import BROWS, LOWER_INNER_LIP, UPPER_INNER_LIP
from stages.layout import load_layout
from tests.memory_stream import MemoryStream

FPS = 25.0
NO_FACE = (5, 6, 7)  # performer frames without a face
LIMITED = (10, 11, 20)  # frames whose geometry was soft-limited
YPR_AMPLITUDE_DEG = (20.0, 8.0, 5.0)


def level_neutral() -> tuple[np.ndarray, tuple[str, ...], float]:
    """A neutral face of the zhang134 layout, eye line level: ``(xy (N, 2) px, names, eye distance px)``.

    The outer eye corners are 60 px apart at y = 100; the inner lips lie at y = 170 (upper) and
    172 (lower), the mouth corners at x = 100 and 140, the brows at y = 80; the other points are
    spread over the face (the signals do not read them).
    """
    names = load_layout("zhang134").point_names
    rng = np.random.default_rng(0)
    xy = rng.uniform([80, 60], [180, 200], (len(names), 2))
    place = {"eye_l_6": (90, 100), "eye_r_6": (150, 100), "mouth_outer_0": (100, 175), "mouth_outer_8": (140, 175)}
    for name, where in place.items():
        xy[names.index(name)] = where
    for k, name in enumerate(UPPER_INNER_LIP + LOWER_INNER_LIP):
        xy[names.index(name)] = (105 + 8 * (k % 4), 170 if name in UPPER_INNER_LIP else 172)
    for k, name in enumerate(BROWS):
        xy[names.index(name)] = (85 + 4 * k, 80)
    return xy, names, 60.0


def mouth_opening(T: int, amplitude: float, peak: int) -> np.ndarray:
    """``(T,)`` eye distances: 0 at frame 0, a single bump of ``amplitude`` at frame ``peak``."""
    t = np.arange(T, dtype=np.float64)
    return amplitude * np.exp(-0.5 * ((t - peak) / 3.0) ** 2) * (t > 0)


def geometry(neutral: np.ndarray, names: tuple[str, ...], eye: float, opening: np.ndarray) -> np.ndarray:
    """``(T, N, 2)``: the neutral with the lower inner lip moved down by ``opening`` eye distances."""
    xy = np.repeat(neutral[None], len(opening), axis=0)
    xy[:, [names.index(n) for n in LOWER_INNER_LIP], 1] += (opening * eye)[:, None]
    return xy


def gradients(T: int, H: int, W: int) -> np.ndarray:
    """``(T, H, W, 3)`` float in [0, 1]: smooth colour ramps that change from frame to frame."""
    y, x = np.mgrid[0:H, 0:W] / max(H, W)
    phase = np.arange(T)[:, None, None] / T
    return np.stack([x + 0 * phase, (y + phase) % 1.0, 0.5 + 0.5 * np.sin(6 * (x + y) + phase * 6)], axis=-1)


def inputs(
    T: int = 40, *, tracked_names: tuple[str, ...] | None = None, size: tuple[int, int] = (64, 48), with_mapped: bool = True
) -> dict[str, Any]:
    """The stage's inputs. ``tracked_names``: the performer's point subset (default: all points).

    Ground truth: target mouth opening ``truth_target_open``, performer ``truth_performer_open``
    (change from frame 0, eye distances); yaw/pitch/roll ``truth_ypr_deg (T, 3)``.
    """
    neutral, names, eye = level_neutral()
    target_open, performer_open = mouth_opening(T, 0.2, T // 2), mouth_opening(T, 0.1, T // 2 + 2)
    target_xy = geometry(neutral, names, eye, target_open)
    performer_xy = geometry(0.8 * neutral + [5.0, 3.0], names, 0.8 * eye, performer_open)
    keep = [names.index(n) for n in (tracked_names or names)]
    valid = np.ones((T, len(keep)), bool)
    valid[list(NO_FACE)] = False
    rng = np.random.default_rng(7)
    t = np.arange(T)
    ypr = np.stack([a * np.sin(2 * np.pi * t / T + k) for k, a in enumerate(YPR_AMPLITUDE_DEG)], axis=1)
    R = Rotation.from_euler("YXZ", ypr, degrees=True).as_matrix()
    examples = np.array([f"ex{k}" for k in range(6)] + ["teeth0", "teeth1"])
    subregions = np.array([f"region{k}" for k in range(4)] + ["teeth"])
    coeff = np.full((T, 5, 8), np.nan)
    coeff[:, :4, :6] = rng.dirichlet(np.ones(6), size=(T, 4))
    coeff[:, 4, 6:] = rng.dirichlet(np.ones(2), size=T)
    limited = np.zeros(T, bool)
    limited[list(LIMITED)] = True
    W, H = size
    performer_frames = (255 * gradients(T, H, W)).astype(np.uint8)
    result_frames = gradients(T, 2 * H, 2 * W)[..., ::-1].astype(np.float16)
    out = {
        "performer": MemoryStream(performer_frames, fps=FPS),
        "result": MemoryStream(result_frames, fps=FPS),
        "target": {
            "xy": target_xy,
            "valid": np.ones((T, len(names)), bool),
            "names": np.array(names),
            "iterations": rng.integers(1, 30, T),
            "input_error_px": rng.random(T),
        },
        "tracked": {
            "xy": performer_xy[:, keep],
            "valid": valid,
            "names": np.array(names)[keep],
            "confidence": rng.random((T, len(keep))).astype(np.float32),
        },
        "pose": {
            "R": R,
            "rvec": Rotation.from_matrix(R).as_rotvec(),
            "tvec": np.zeros((T, 3)),
            "reproj_err_px": rng.random(T),
            "valid": valid.any(axis=1),
        },
        "similarity": {"params": np.tile([1.0, 0, 0, 0], (T, 1)), "residual_px": rng.random(T), "valid": valid.any(axis=1)},
        "coefficients": {"coeff": coeff, "subregions": subregions, "examples": examples},
        "truth_target_open": target_open,
        "truth_performer_open": performer_open,
        "truth_ypr_deg": ypr,
    }
    if with_mapped:
        out["mapped"] = {
            "xy": target_xy,
            "valid": np.ones((T, len(names)), bool),
            "names": np.array(names),
            "range_limited": limited,
            "lips_clamped": np.zeros(T, bool),
        }
    return out
