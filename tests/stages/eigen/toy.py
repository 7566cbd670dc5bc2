"""A toy eigenfeature model trained on :mod:`tests.stages.eigen.scene` (4 parameters, 2 features)."""

from __future__ import annotations

import numpy as np

from stages.eigen.model import EigenModel, fit_eigen_model, fit_geometry_map
from tests.stages.eigen import scene

MOTION = np.zeros((4, len(scene.NAMES), 2))
MOTION[0, 2] = (0.0, 5.0)  # parameter 0 moves a_2 down 5 px
MOTION[3, 4] = (3.0, 0.0)  # parameter 3 moves b_1 right 3 px


def random_similarity(rng: np.random.Generator) -> np.ndarray:
    s, ang = rng.uniform(0.9, 1.1), np.radians(rng.uniform(-8.0, 8.0))
    return np.array([s * np.cos(ang), s * np.sin(ang), rng.uniform(-5, 5), rng.uniform(-5, 5)])


def toy_model(*, samples: int = 60, q: int = 6, seed: int = 0, blur_px: float = 0.0, normalize: bool = False) -> EigenModel:
    rng = np.random.default_rng(seed)
    params = rng.random((samples, 4))
    sims = [random_similarity(rng) for _ in params]
    renders = ((scene.scene(p, T), T) for p, T in zip(params, sims))
    geometry = fit_geometry_map(params, scene.NEUTRAL[None] + np.einsum("mc,cnk->mnk", params, MOTION))
    return fit_eigen_model(
        renders,
        np.zeros((samples, 3)),
        params,
        windows=scene.windows(),
        neutral=scene.NEUTRAL,
        point_names=scene.NAMES,
        param_names=("p0", "p1", "p2", "p3"),
        rigid=tuple(range(len(scene.NAMES))),
        param_range=(0.0, 1.0),
        geometry=geometry,
        q=q,
        blur_px=blur_px,
        normalize=normalize,
    )
