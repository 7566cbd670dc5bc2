"""Expression mapping's geometric step: displacements carried onto the target's neutral."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

import stages.geometry.mapping
from runner.stage import StageError
from stages.geometry.compensate import apply_similarity
from stages.geometry.mapping import ExpressionMap, displacement_transforms, map_expression
from stages.layout import load_layout
from tests.stages.geometry.synthetic import context


def rotation(angle: float) -> np.ndarray:
    return np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])


def test_similarity_mode_scales_and_rotates_displacements():
    rng = np.random.default_rng(0)
    target = rng.uniform(50, 250, (12, 2))
    scale, angle = 0.6, 0.2
    # the performer's neutral: the target's face scaled by 1/0.6 and turned by -0.2 rad
    inverse = np.array([np.cos(-angle) / scale, np.sin(-angle) / scale, 30.0, -12.0])
    performer = apply_similarity(inverse, target)
    d = rng.normal(0, 4.0, (5, 12, 2))
    transforms = displacement_transforms(performer, target, np.arange(6))
    xy = map_expression(d, target, transforms)
    expected = target[None] + scale * np.einsum("ij,tnj->tni", rotation(angle), d)
    np.testing.assert_allclose(xy, expected, atol=1e-9)
    np.testing.assert_allclose(map_expression(d, target, displacement_transforms(performer, target, np.arange(6),
                                                                                mode="none")), target + d)


def test_region_mode_uses_each_region_size():
    rng = np.random.default_rng(1)
    performer = rng.uniform(0, 100, (9, 2))
    target = performer.copy()
    target[:4] = 2.0 * (performer[:4] - performer[:4].mean(axis=0)) + performer[:4].mean(axis=0)
    target[4:8] = 0.5 * (performer[4:8] - performer[4:8].mean(axis=0)) + performer[4:8].mean(axis=0)
    transforms = displacement_transforms(performer, target, np.arange(9), mode="region",
                                         regions=[np.arange(4), np.arange(4, 8), np.array([8])])
    np.testing.assert_allclose(transforms[:4, 0, 0], 2.0, rtol=1e-12)
    np.testing.assert_allclose(transforms[4:8, 0, 0], 0.5, rtol=1e-12)
    np.testing.assert_allclose(transforms[:, 1, 0], 0.0, atol=1e-12)
    global_scale = displacement_transforms(performer, target, np.arange(9))[8]
    np.testing.assert_allclose(transforms[8], global_scale, atol=1e-12)  # too small a region: global


def test_stage_maps_onto_the_pack_neutral(tmp_path, monkeypatch):
    layout = load_layout("zhang134")
    rng = np.random.default_rng(2)
    target_all = rng.uniform(40, 200, (layout.n_points, 2))
    monkeypatch.setattr(stages.geometry.mapping, "load_pack",
                        lambda path: SimpleNamespace(layout=layout, neutral=SimpleNamespace(points=target_all)))
    names = np.array([layout.point_names[i] for i in layout.tracked])
    target = target_all[list(layout.tracked)]
    performer = apply_similarity(np.array([1.5, 0.0, 10.0, 5.0]), target)
    d = rng.normal(0, 3.0, (4, len(names), 2))
    bundle = {"d": d, "valid": np.ones((4, len(names)), bool), "names": names, "neutral": performer}
    bundle["valid"][2, 5] = False
    out = ExpressionMap().run({"displacements": bundle, "pack": tmp_path}, {}, context(tmp_path))["points"]
    tracked = list(layout.tracked)
    assert out["xy"].shape == (4, layout.n_points, 2) and list(out["names"]) == list(layout.point_names)
    np.testing.assert_allclose(out["xy"][:, tracked], target + d / 1.5, atol=1e-9)
    others = np.setdiff1d(np.arange(layout.n_points), tracked)
    np.testing.assert_array_equal(out["xy"][:, others], np.broadcast_to(target_all[others], (4, len(others), 2)))
    assert out["valid"][:, tracked].sum() == 4 * len(tracked) - 1 and not out["valid"][:, others].any()
    assert not out["valid"][2, tracked[5]]
    region = ExpressionMap().run({"displacements": bundle, "pack": tmp_path}, {"mode": "region"},
                                 context(tmp_path))["points"]
    np.testing.assert_allclose(region["xy"][:, tracked], target + d / 1.5, atol=1e-9)  # one scale for all here
    del bundle["neutral"]
    with pytest.raises(StageError, match="neutral"):
        ExpressionMap().run({"displacements": bundle, "pack": tmp_path}, {}, context(tmp_path))
