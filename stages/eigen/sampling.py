"""Samplings of the animation-parameter and head-rotation space for the training renders
(Valente & Dugelay, "Early results on synthetic images").

Animation parameters here are the face generator's expression controls (``scripts/facegen``,
each in [0, 1], 0 = neutral); the paper's FAP values {-1, -0.5, 0, 0.5, 1} span each FAP's range,
so on the controls' one-sided range they become {0, 0.25, 0.5, 0.75, 1}. Angles are degrees,
columns (yaw, pitch, roll) = rotation about Y, X, Z.
"""

from __future__ import annotations

import itertools

import numpy as np

PAPER_LEVELS = (0.0, 0.25, 0.5, 0.75, 1.0)  # the paper's {-1, -0.5, 0, 0.5, 1} on [0, 1]
PAPER_ANGLES_DEG = (-3.0, 0.0, 3.0)  # X and Y rotation


def paper_sampling(n_params: int) -> tuple[np.ndarray, np.ndarray]:
    """Each parameter alone over :data:`PAPER_LEVELS`, every expression under the 9 orientations
    X, Y in :data:`PAPER_ANGLES_DEG` (roll 0). The neutral, shared by all parameters, once.

    Returns
    -------
    controls : (m, n_params) float64
    angles : (m, 3) float64
        (yaw, pitch, roll) deg; ``m = (4 n_params + 1) * 9``.
    """
    if n_params < 1:
        raise ValueError(f"expected n_params >= 1, got {n_params}")
    expressions = [np.zeros(n_params)]
    for k, level in itertools.product(range(n_params), PAPER_LEVELS[1:]):
        c = np.zeros(n_params)
        c[k] = level
        expressions.append(c)
    poses = [(yaw, pitch, 0.0) for pitch in PAPER_ANGLES_DEG for yaw in PAPER_ANGLES_DEG]
    controls = np.array([c for c in expressions for _ in poses])
    angles = np.array([p for _ in expressions for p in poses], dtype=np.float64)
    return controls, angles


def rich_sampling(n_params: int, count: int, *, seed: int = 0, active: float = 0.35,
                  max_deg: tuple[float, float, float] = (25.0, 15.0, 10.0)) -> tuple[np.ndarray, np.ndarray]:
    """Random combinations of parameters under a wider range of head rotations.

    Each parameter is active with probability ``active`` and then uniform in [0, 1]; angles are
    uniform in ``[-max_deg, max_deg]`` per axis (yaw, pitch, roll).

    Returns
    -------
    controls : (count, n_params) float64
    angles : (count, 3) float64
        (yaw, pitch, roll) deg.
    """
    if count < 1 or not 0.0 < active <= 1.0:
        raise ValueError(f"expected count >= 1 and 0 < active <= 1, got count={count}, active={active}")
    rng = np.random.default_rng(seed)
    on = rng.random((count, n_params)) < active
    controls = np.where(on, rng.random((count, n_params)), 0.0)
    angles = rng.uniform(-1.0, 1.0, (count, 3)) * np.asarray(max_deg, dtype=np.float64)
    return controls, angles


def rotation_angles(R: np.ndarray) -> np.ndarray:
    """(yaw, pitch, roll) deg ``(..., 3)`` of rotations ``(..., 3, 3)`` with
    ``R = Rz(roll) Ry(yaw) Rx(pitch)`` (the generator's and the fixtures' convention)."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"expected rotations (..., 3, 3), got {R.shape}")
    yaw = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    pitch = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    roll = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.degrees(np.stack([yaw, pitch, roll], axis=-1))
