"""A toy face for the propagation tests: 4 facial feature regions of 6 points, a 3-level hierarchy,
and captured expressions built from known displacement modes (ground truth by construction)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

REGIONS = {"left_eye": range(0, 6), "right_eye": range(6, 12), "nose": range(12, 18), "mouth": range(18, 24)}
N_POINTS = 24
NOSE_TIP = 14


@dataclass(frozen=True)
class ToySet:
    name: str
    level: int
    points: tuple[int, ...]


def toy_hierarchy() -> list[ToySet]:
    """1 global set, 4 region sets (each with a bridge point of the next region), 8 half-region sets."""
    sets = [ToySet("face", 0, tuple(range(N_POINTS)))]
    names = list(REGIONS)
    for k, name in enumerate(names):
        bridge = REGIONS[names[(k + 1) % 4]][0]
        sets.append(ToySet(name, 1, tuple(REGIONS[name]) + (bridge,)))
    for name in names:
        pts = tuple(REGIONS[name])
        sets.append(ToySet(f"{name}_a", 2, pts[:4]))
        sets.append(ToySet(f"{name}_b", 2, pts[3:]))
    return sets


def toy_neutral() -> np.ndarray:
    """(24, 2) px: each region a ring of 6 points around its centre."""
    centres = {"left_eye": (40, 40), "right_eye": (80, 40), "nose": (60, 65), "mouth": (60, 90)}
    angles = np.linspace(0, 2 * np.pi, 6, endpoint=False)
    ring = np.stack([np.cos(angles), np.sin(angles)], axis=1) * 8.0
    return np.concatenate([ring + np.array(centres[name], dtype=float) for name in REGIONS])


def region_modes() -> np.ndarray:
    """(8, 24, 2) displacement modes: each region translates (x, y) on its own."""
    modes = []
    for name in REGIONS:
        for axis in (0, 1):
            m = np.zeros((N_POINTS, 2))
            m[list(REGIONS[name]), axis] = 1.0
            modes.append(m)
    return np.stack(modes)


def low_rank_modes(rank: int, seed: int) -> np.ndarray:
    """(rank, 24, 2) random smooth-ish displacement modes shared by the whole face."""
    rng = np.random.default_rng(seed)
    return rng.normal(size=(rank, N_POINTS, 2))


def expressions(modes: np.ndarray, count: int, *, seed: int, scale: float = 4.0) -> np.ndarray:
    """(count, 24, 2) displacements, random combinations of ``modes``, px."""
    rng = np.random.default_rng(seed)
    return np.einsum("km,mnc->knc", rng.normal(size=(count, modes.shape[0])) * scale, modes)
