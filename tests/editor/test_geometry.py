"""Edit geometry against independent computations: propagation (Sec. 10.1), touch-up of a base
geometry, keyframe interpolation and the in-betweens of Sec. 14.2."""

from __future__ import annotations

import numpy as np
import pytest

from editor.geometry import edited_geometry, inbetweens, interpolate_keyframes
from stages.actor_pack import load_pack
from stages.propagation.hierarchical_pca import fit_hierarchical_pca
from stages.propagation.propagate import motion_propagation
from tests.editor.conftest import PACK


@pytest.fixture(scope="module")
def model():
    pack = load_pack(PACK)
    return fit_hierarchical_pca(
        pack.neutral.points,
        pack.captured_points,
        pack.layout.feature_point_sets,
        n_components=8,
        point_names=pack.layout.point_names,
    )


def test_edit_from_the_neutral_is_motion_propagation_of_the_pinned_points(model):
    lip, corner = 80, 100
    pinned = {lip: model.neutral[lip] + [0.5, 6.0], corner: model.neutral[corner] + [-2.0, 1.0]}
    result = edited_geometry(model, pinned)
    d = np.zeros((1, model.n_points, 2))
    known = np.zeros((1, model.n_points), bool)
    for i, xy in pinned.items():
        d[0, i], known[0, i] = xy - model.neutral[i], True
    expected = model.neutral + motion_propagation(model, d, known).displacements[0]
    np.testing.assert_allclose(result, expected, atol=1e-9)
    for i, xy in pinned.items():
        np.testing.assert_array_equal(result[i], xy)
    np.testing.assert_array_equal(edited_geometry(model, {}), model.neutral)


def test_touch_up_keeps_the_base_where_nothing_moved(model):
    rng = np.random.default_rng(3)
    base = model.neutral + rng.normal(0.0, 2.0, model.neutral.shape)
    held = edited_geometry(model, {7: base[7], 90: base[90]}, base=base)
    np.testing.assert_allclose(held, base, atol=1e-6)
    moved = edited_geometry(model, {90: base[90] + [0.0, 5.0]}, base=base)
    np.testing.assert_allclose(moved[90], base[90] + [0.0, 5.0])
    # The change is the propagated displacement of the pinned point alone, added to the base.
    from_neutral = edited_geometry(model, {90: model.neutral[90] + [0.0, 5.0]}) - edited_geometry(model, {90: model.neutral[90]})
    np.testing.assert_allclose(moved - base, from_neutral, atol=1e-6)


@pytest.mark.parametrize(
    "pinned, base", [({200: (1.0, 2.0)}, None), ({3: (np.nan, 2.0)}, None), ({3: (1.0, 2.0)}, np.zeros((3, 2)))]
)
def test_edit_rejects_bad_input(model, pinned, base):
    with pytest.raises(ValueError):
        edited_geometry(model, pinned, base=base)


def test_keyframes_interpolate_linearly_in_time():
    rng = np.random.default_rng(0)
    times = np.array([0.5, 1.0, 2.2])
    keys = rng.normal(size=(3, 4, 2))
    frames = interpolate_keyframes(times, keys, fps=5.0)
    assert frames.shape == (9, 4, 2)  # 0.5 .. 2.1 s in steps of 0.2 s
    for k, frame in enumerate(frames):
        t = 0.5 + k / 5.0
        for p in range(4):
            for c in range(2):
                assert frame[p, c] == pytest.approx(np.interp(t, times, keys[:, p, c]), abs=1e-12)
    np.testing.assert_allclose(interpolate_keyframes(np.array([0.0, 1.0]), keys[:2], fps=4.0)[[0, -1]], keys[:2])
    np.testing.assert_array_equal(interpolate_keyframes(np.array([3.0]), keys[:1], fps=30.0), keys[:1])


@pytest.mark.parametrize("times, fps", [([1.0, 1.0], 10.0), ([0.0, 1.0], 0.0), ([0.0, np.nan], 10.0)])
def test_keyframes_reject_bad_input(times, fps):
    with pytest.raises(ValueError):
        interpolate_keyframes(np.array(times), np.zeros((2, 3, 2)), fps=fps)


def test_five_inbetweens_at_sixths():
    a, b = np.zeros((2, 2)), np.ones((2, 2)) * 6.0
    np.testing.assert_allclose(inbetweens(a, b)[:, 0, 0], [1.0, 2.0, 3.0, 4.0, 5.0])


def test_performance_files_are_checked(tmp_path):
    from editor.engine import read_performance

    layout = load_pack(PACK).layout
    good = tmp_path / "good.npz"
    np.savez(good, target_xy=np.zeros((2, layout.n_points, 2)), target_names=np.array(layout.point_names))
    assert read_performance(good, layout).shape == (2, layout.n_points, 2)
    for name, fields in {
        "missing": {"xy": np.zeros((2, layout.n_points, 2))},
        "shape": {"target_xy": np.zeros((2, 3, 2))},
        "names": {"target_xy": np.zeros((2, layout.n_points, 2)), "target_names": np.array(["x"] * layout.n_points)},
        "nan": {"target_xy": np.full((2, layout.n_points, 2), np.nan)},
    }.items():
        path = tmp_path / f"{name}.npz"
        np.savez(path, **fields)
        with pytest.raises(ValueError, match="target_"):
            read_performance(path, layout)
