"""Stage wrappers: propagate.train on pack.load's layout and geometry bundles, propagate.hierarchical on bundles."""

from pathlib import Path

import numpy as np
import pytest

from runner.registry import check_stage_class
from runner.stage import Context, StageError
from stages.actor_pack import load_pack
from stages.layout import FeaturePointSet, Layout, Subregion
from stages.pack.bundles import layout_to_bundle, pack_to_bundles
from stages.propagation.hierarchical_pca import HierarchicalPCA, fit_hierarchical_pca
from stages.propagation.propagate import motion_propagation
from stages.propagation.stage import HierarchicalPropagation, TrainHierarchicalPCA
from tests.stages.propagation.toy_face import N_POINTS, expressions, low_rank_modes, toy_hierarchy, toy_neutral

NAMES = tuple(f"p{i}" for i in range(N_POINTS))
PARAMS = {"stop_progress_px": 1e-6, "max_iterations": 500}
FPS = np.array(25.0)


def context(tmp_path: Path) -> Context:
    return Context(device="cpu", files_dir=lambda port: tmp_path / port)


@pytest.fixture(scope="module")
def model() -> HierarchicalPCA:
    captured = toy_neutral() + expressions(low_rank_modes(6, seed=71), 35, seed=72)
    return fit_hierarchical_pca(toy_neutral(), captured, toy_hierarchy(), n_components=6, point_names=NAMES)


def toy_layout() -> Layout:
    """A layout over the toy face: its hierarchy, one subregion, four rigid and three tracked points."""
    sets = tuple(FeaturePointSet(s.name, s.level, s.points) for s in toy_hierarchy())
    return Layout(
        name="toy",
        point_names=NAMES,
        subregions=(Subregion("face", (0, 1, 2), ()),),
        no_blend=(),
        feature_point_sets=sets,
        rigid=(0, 1, 2, 3),
        tracked=(0, 1, 2),
    )


def test_train_reads_layout_and_geometry_and_returns_a_model_bundle(tmp_path):
    captured = toy_neutral() + expressions(low_rank_modes(6, seed=71), 35, seed=72)
    layout = layout_to_bundle(toy_layout())
    geometry = {
        "names": np.array(NAMES),
        "neutral": toy_neutral(),
        "captured": captured,
        "examples": captured[:3],
        "size": np.array([64, 64]),
    }
    params = {"n_components": 6, "variance_kept": 1.0}
    check_stage_class(TrainHierarchicalPCA)
    out = TrainHierarchicalPCA().run({"layout": layout, "geometry": geometry}, params, context(tmp_path))
    bundle = out["pca_model"]
    assert all(isinstance(v, np.ndarray) and v.dtype != object for v in bundle.values())
    expected = fit_hierarchical_pca(toy_neutral(), captured, toy_hierarchy(), n_components=6, point_names=NAMES)
    np.testing.assert_array_equal(bundle["components"], expected.to_bundle()["components"])
    with pytest.raises(StageError, match="propagate.train: pack_geometry bundle: key 'names'"):
        TrainHierarchicalPCA().run(
            {"layout": layout, "geometry": geometry | {"names": np.array(NAMES[::-1])}}, params, context(tmp_path)
        )


def test_points_and_displacements_inputs_agree(model, tmp_path):
    truth = expressions(low_rank_modes(6, seed=71), 5, seed=73)
    valid = np.random.default_rng(74).random((5, N_POINTS)) < 0.5
    valid[2] = False
    stage = HierarchicalPropagation()
    pca = model.to_bundle()
    outputs = stage.run(
        {"pca_model": pca, "displacements": {"d": truth, "valid": valid, "names": np.array(NAMES), "fps": FPS}},
        PARAMS,
        context(tmp_path),
    )
    by_d = outputs["displacements"]
    np.testing.assert_allclose(outputs["points"]["xy"], toy_neutral() + by_d["d"], atol=1e-12)
    np.testing.assert_array_equal(outputs["points"]["valid"], by_d["valid"])
    by_xy = stage.run(
        {"pca_model": pca, "points": {"xy": toy_neutral() + truth, "valid": valid, "names": np.array(NAMES)}},
        PARAMS,
        context(tmp_path),
    )["displacements"]
    np.testing.assert_allclose(by_xy["d"], by_d["d"], atol=1e-9)
    direct = motion_propagation(model, truth, valid, **PARAMS)
    np.testing.assert_array_equal(by_d["d"], direct.displacements)
    np.testing.assert_array_equal(by_d["iterations"], direct.iterations)
    assert by_d["valid"].shape == (5, N_POINTS) and not by_d["valid"][2].any() and by_d["valid"][[0, 1, 3, 4]].all()
    assert by_d["fps"] == 25.0 and tuple(by_d["names"]) == NAMES


def test_bad_inputs_raise_stage_errors(model, tmp_path):
    stage = HierarchicalPropagation()
    pca = model.to_bundle()
    d = {"d": np.zeros((2, N_POINTS, 2)), "valid": np.ones((2, N_POINTS), bool)}
    xy = {"xy": np.zeros((2, N_POINTS, 2)), "valid": np.ones((2, N_POINTS), bool)}
    with pytest.raises(StageError, match="exactly one"):
        stage.run({"pca_model": pca, "displacements": d, "points": xy}, PARAMS, context(tmp_path))
    with pytest.raises(StageError, match="names"):
        stage.run({"pca_model": pca, "displacements": {**d, "names": np.array(NAMES[::-1])}}, PARAMS, context(tmp_path))
    with pytest.raises(StageError, match="'d'"):
        stage.run({"pca_model": pca, "displacements": {**d, "d": np.zeros((2, 7, 2))}}, PARAMS, context(tmp_path))
    with pytest.raises(StageError, match="valid"):
        stage.run({"pca_model": pca, "points": {"xy": xy["xy"]}}, PARAMS, context(tmp_path))
    broken = {k: v for k, v in pca.items() if k != "components"}
    with pytest.raises(StageError, match="propagate.hierarchical: input 'pca_model': missing field.*components"):
        stage.run({"pca_model": broken, "displacements": d}, PARAMS, context(tmp_path))
    nan = {**d, "d": np.full((2, N_POINTS, 2), np.nan)}
    with pytest.raises(StageError, match="propagate.hierarchical: input 'displacements': .*NaN"):
        stage.run({"pca_model": pca, "displacements": nan}, PARAMS, context(tmp_path))


def test_parameter_ranges_are_declared():
    """Out-of-range values are refused when the graph is loaded (Param.problem), not in run()."""
    declared = {(cls.name, p.name): p for cls in (TrainHierarchicalPCA, HierarchicalPropagation) for p in cls.params}
    for key, bad, good in [
        (("propagate.hierarchical", "max_iterations"), 0, 1),
        (("propagate.hierarchical", "stop_progress_px"), -1e-3, 0.0),
        (("propagate.train", "n_components"), 0, 1),
        (("propagate.train", "variance_kept"), 1.5, 1.0),
    ]:
        assert "out of range" in declared[key].problem(bad) and declared[key].problem(good) is None, key


def test_stage_classes_declare_a_valid_contract():
    for cls in (TrainHierarchicalPCA, HierarchicalPropagation):
        check_stage_class(cls)


PACK = Path(__file__).resolve().parents[3] / "fixtures" / "packs" / "target"


def test_train_and_propagate_on_the_fixture_pack(tmp_path):
    pack = pack_to_bundles(load_pack(PACK))
    bundle = TrainHierarchicalPCA().run(
        {"layout": pack["layout"], "geometry": pack["geometry"]}, {"n_components": 8, "variance_kept": 1.0}, context(tmp_path)
    )["pca_model"]
    model = HierarchicalPCA.from_bundle(bundle)
    assert sorted(model.levels.tolist()) == [0] + [1] * 4 + [2] * 16
    with np.load(PACK / "captured.npz", allow_pickle=False) as npz:
        captured = npz["points"]
    names = np.array(model.point_names)
    valid = np.zeros((len(captured), model.n_points), dtype=bool)
    valid[:, ::8] = True  # 17 points spread over the layout
    out = HierarchicalPropagation().run(
        {"pca_model": bundle, "points": {"xy": captured, "valid": valid, "names": names}}, PARAMS, context(tmp_path)
    )["displacements"]
    truth = captured - model.neutral
    error = np.linalg.norm(out["d"] - truth, axis=2).mean()
    zero_fill = np.linalg.norm(np.where(valid[..., None], truth, 0.0) - truth, axis=2).mean()
    assert error < 0.5 * zero_fill
