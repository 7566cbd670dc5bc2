"""Samplings of the animation-parameter and head-rotation space for the training renders
(Valente & Dugelay, "Early results on synthetic images").

The paper's FAP values {-1, -0.5, 0, 0.5, 1} span each FAP's range; a face model gives its own
levels: the face generator's expression controls (``stages.eigen.facegen``, each in [0, 1], 0 =
neutral) take {0, 0.25, 0.5, 0.75, 1} (:data:`PAPER_LEVELS`), the PCA parameters of a pack's
captured geometries {-2, -1, 0, 1, 2} standard deviations (:mod:`.packface`). Angles are degrees,
columns (yaw, pitch, roll) = rotation about Y, X, Z.
"""

from __future__ import annotations

import itertools

import numpy as np

PAPER_LEVELS = (0.0, 0.25, 0.5, 0.75, 1.0)  # the paper's {-1, -0.5, 0, 0.5, 1} on [0, 1]
PAPER_ANGLES_DEG = (-3.0, 0.0, 3.0)  # X and Y rotation


def paper_sampling(n_params: int, *, levels: tuple[float, ...] = PAPER_LEVELS) -> tuple[np.ndarray, np.ndarray]:
    """Each parameter alone over ``levels``, every expression under the 9 orientations X, Y in
    :data:`PAPER_ANGLES_DEG` (roll 0). The neutral (all parameters 0), shared by all parameters,
    once; ``levels`` must contain 0.

    Returns
    -------
    controls : (m, n_params) float64
    angles : (m, 3) float64
        (yaw, pitch, roll) deg; ``m = ((len(levels) - 1) n_params + 1) * 9``.
    """
    if n_params < 1 or 0.0 not in levels:
        raise ValueError(f"expected n_params >= 1 and levels containing 0, got {n_params} and {levels}")
    expressions = [np.zeros(n_params)]
    for k, level in itertools.product(range(n_params), [v for v in levels if v != 0.0]):
        c = np.zeros(n_params)
        c[k] = level
        expressions.append(c)
    poses = [(yaw, pitch, 0.0) for pitch in PAPER_ANGLES_DEG for yaw in PAPER_ANGLES_DEG]
    controls = np.array([c for c in expressions for _ in poses])
    angles = np.array([p for _ in expressions for p in poses], dtype=np.float64)
    return controls, angles


def rich_sampling(
    n_params: int,
    count: int,
    *,
    seed: int = 0,
    active: float = 0.35,
    span: tuple[float, float] = (0.0, 1.0),
    max_deg: tuple[float, float, float] = (25.0, 15.0, 10.0),
) -> tuple[np.ndarray, np.ndarray]:
    """Random combinations of parameters under a wider range of head rotations.

    Each parameter is active with probability ``active`` and then uniform in ``span`` (0
    otherwise); angles are uniform in ``[-max_deg, max_deg]`` per axis (yaw, pitch, roll).

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
    controls = np.where(on, rng.uniform(span[0], span[1], (count, n_params)), 0.0)
    angles = rng.uniform(-1.0, 1.0, (count, 3)) * np.asarray(max_deg, dtype=np.float64)
    return controls, angles
