"""A tiny synthetic actor pack with known answers, built in memory for the synthesis tests.

Six face subregions tile a 3 x 2 grid of cells over a 4 x 3 grid of points; a teeth subregion
(four extra points, a small square) lies inside the bottom-middle cell. Every example
expression moves the points by a few pixels and carries its own smooth texture, rendered in its
own geometry, so aligned examples and synthesized images can be predicted exactly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stages.actor_pack import ActorPack, Expression
from stages.layout import parse_layout

W, H = 96, 80
GRID_X = (18.0, 38.0, 58.0, 78.0)
GRID_Y = (14.0, 38.0, 62.0)


def grid_name(i: int, j: int) -> str:
    return f"g{i}{j}"


def layout_dict() -> dict:
    names = [grid_name(i, j) for j in range(3) for i in range(4)] + ["t0", "t1", "t2", "t3"]
    cells = []
    for j in range(2):
        for i in range(3):
            poly = [grid_name(i, j), grid_name(i + 1, j), grid_name(i + 1, j + 1), grid_name(i, j + 1)]
            cells.append({"name": f"cell{i}{j}", "polygon": poly, "points": []})
    cells.append({"name": "teeth", "polygon": ["t0", "t1", "t2", "t3"], "points": [], "teeth": True})
    return {
        "name": "synthetic",
        "points": names,
        "subregions": cells,
        "no_blend": [["cell11", "teeth"], ["cell00", "cell10"]],
        "feature_point_sets": [{"name": "all", "level": 0, "points": names}],
        "rigid": names[:4],
        "tracked": names[:4],
    }


def base_points() -> np.ndarray:
    grid = [(GRID_X[i], GRID_Y[j]) for j in range(3) for i in range(4)]
    teeth = [(44.0, 46.0), (52.0, 46.0), (52.0, 54.0), (44.0, 54.0)]
    return np.array(grid + teeth, np.float64)


def texture(points: np.ndarray, seed: int) -> np.ndarray:
    """(H, W, 3) uint8: a smooth texture attached to the face geometry ``points`` (N, 2).

    Colour is a smooth function of the position relative to the geometry's first grid point and
    its grid spacing, so an image rendered in one geometry and warped to another agrees with the
    same texture rendered there (up to the piecewise-affine approximation).
    """
    rng = np.random.default_rng(seed)
    fx, fy, ph = rng.uniform(0.15, 0.35), rng.uniform(0.15, 0.35), rng.uniform(0, 6.28, 3)
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    u, v = x - points[0, 0], y - points[0, 1]
    img = np.stack([0.5 + 0.35 * np.sin(fx * u + ph[k]) * np.cos(fy * v + ph[k] / 2) for k in range(3)], -1)
    return np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)


def make_pack(*, n_examples: int = 4, n_teeth: int = 2, seed: int = 0) -> ActorPack:
    rng = np.random.default_rng(seed)
    layout = parse_layout(layout_dict())
    std = base_points()

    def expression(name: str, k: int) -> Expression:
        pts = std + rng.normal(0, 1.5, std.shape)
        return Expression(name, texture(pts, seed * 100 + k), pts)

    examples = [expression(f"ex{k}", k) for k in range(n_examples)]
    teeth = [expression(f"teeth{k}", 50 + k) for k in range(n_teeth)]
    neutral = Expression("neutral", texture(std, seed * 100 + 99), std.copy())
    standard = Expression("standard", texture(std, seed * 100 + 98), std.copy())
    return ActorPack(
        path=Path("<synthetic>"),
        name="synthetic",
        layout=layout,
        neutral=neutral,
        standard=standard,
        examples=examples,
        teeth_examples=teeth,
        captured_points=np.stack([e.points for e in examples]),
        model3d=np.zeros((len(std), 3)),
        intrinsics=np.eye(3),
        image_size=(W, H),
    )
