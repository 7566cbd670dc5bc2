"""A synthetic two-feature "face" whose appearance is an exact function of its parameters, seen
through a known similarity: the ground truth of the eigenfeature tests."""

from __future__ import annotations

import numpy as np

from stages.eigen.patches import feature_windows

NAMES = ("a_0", "a_1", "a_2", "b_0", "b_1", "b_2")
NEUTRAL = np.array([[30.0, 30.0], [50.0, 28.0], [40.0, 45.0], [90.0, 60.0], [110.0, 62.0], [100.0, 75.0]])
FEATURES = {"a": ("a_",), "b": ("b_",)}
CENTRES = np.array([[36.0, 32.0], [45.0, 40.0], [95.0, 63.0], [105.0, 70.0]])  # one blob per parameter
SIZE = (160, 120)  # W, H


def windows():
    return feature_windows(NEUTRAL, NAMES, margin=0.25, step=1.0, features=FEATURES)


def appearance(u: np.ndarray, params: np.ndarray) -> np.ndarray:
    """Luma in [0, 1] at neutral-frame positions ``u (..., 2)``: a smooth texture plus one
    Gaussian blob per parameter, scaled by it."""
    x, y = u[..., 0], u[..., 1]
    value = 0.45 + 0.12 * np.sin(x / 7.0) * np.cos(y / 9.0) + 0.08 * np.sin((x + 2 * y) / 11.0)
    for centre, p in zip(CENTRES, params):
        value = value + 0.3 * p * np.exp(-((x - centre[0]) ** 2 + (y - centre[1]) ** 2) / (2 * 4.0**2))
    return value


def scene(params: np.ndarray, similarity: np.ndarray, size: tuple[int, int] = SIZE) -> np.ndarray:
    """RGB uint8 image ``(H, W, 3)`` of the face with ``params`` placed by ``similarity`` (a, b, tx, ty)."""
    a, b, tx, ty = similarity
    w, h = size
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    det = a * a + b * b
    dx, dy = xs - tx, ys - ty
    u = np.stack([(a * dx + b * dy) / det, (-b * dx + a * dy) / det], axis=-1)  # T^-1(x)
    luma = np.clip(appearance(u, params), 0.0, 1.0)
    return np.repeat(np.round(luma * 255.0).astype(np.uint8)[..., None], 3, axis=2)
