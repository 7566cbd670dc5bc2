"""Offline hierarchical PCA: subspaces against an independent eigendecomposition, bundle round trip."""

import io

import numpy as np
import pytest

from stages.propagation.hierarchical_pca import HierarchicalPCA, fit_hierarchical_pca
from tests.stages.propagation.toy_face import expressions, low_rank_modes, toy_hierarchy, toy_neutral


@pytest.fixture(scope="module")
def captured() -> np.ndarray:
    noise = np.random.default_rng(3).normal(scale=0.2, size=(36, 24, 2))
    return toy_neutral() + expressions(low_rank_modes(12, seed=1), 36, seed=2) + noise


def test_subspaces_match_covariance_eigenvectors(captured):
    sets = toy_hierarchy()
    model = fit_hierarchical_pca(toy_neutral(), captured, sets, n_components=5)
    for fps, mean, u, ratio in zip(sets, model.means, model.components, model.explained_variance):
        x = (captured - toy_neutral())[:, list(fps.points)].reshape(len(captured), -1)
        np.testing.assert_allclose(mean, x.mean(axis=0), atol=1e-12)
        cov = np.cov(x, rowvar=False)
        eigval, eigvec = np.linalg.eigh(cov)
        top = eigvec[:, ::-1][:, : u.shape[1]]
        assert u.shape[1] == min(5, x.shape[1])
        np.testing.assert_allclose(u.T @ u, np.eye(u.shape[1]), atol=1e-12)
        # same subspace: the projectors agree
        np.testing.assert_allclose(u @ u.T, top @ top.T, atol=1e-8)
        np.testing.assert_allclose(ratio, eigval[::-1][: u.shape[1]] / eigval.sum(), atol=1e-10)


def test_variance_kept_keeps_fewest_components_reaching_it(captured):
    sets = toy_hierarchy()
    model = fit_hierarchical_pca(toy_neutral(), captured, sets, n_components=10, variance_kept=0.8)
    for ratio in model.explained_variance:
        cumulative = np.cumsum(ratio)
        assert cumulative[-1] >= 0.8 - 1e-12
        assert ratio.size == 1 or cumulative[-2] < 0.8


def test_rank_deficient_set_keeps_only_its_rank():
    modes = low_rank_modes(3, seed=4)
    captured = toy_neutral() + expressions(modes, 30, seed=5)
    model = fit_hierarchical_pca(toy_neutral(), captured, toy_hierarchy(), n_components=8)
    assert all(u.shape[1] == 3 for u in model.components)


def test_bundle_round_trip_through_npz_without_pickle(captured):
    names = [f"p{i}" for i in range(24)]
    model = fit_hierarchical_pca(toy_neutral(), captured, toy_hierarchy(), n_components=6, point_names=names)
    buffer = io.BytesIO()
    np.savez(buffer, **model.to_bundle())
    buffer.seek(0)
    with np.load(buffer, allow_pickle=False) as npz:
        back = HierarchicalPCA.from_bundle(dict(npz))
    assert back.set_names == model.set_names and back.point_names == model.point_names
    np.testing.assert_array_equal(back.levels, model.levels)
    for a, b in zip(back.components, model.components):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(back.points, model.points):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(back.means, model.means):
        np.testing.assert_array_equal(a, b)


def test_bundle_missing_field_names_it(captured):
    bundle = fit_hierarchical_pca(toy_neutral(), captured, toy_hierarchy()).to_bundle()
    del bundle["components"]
    with pytest.raises(ValueError, match="components"):
        HierarchicalPCA.from_bundle(bundle)


def test_bad_feature_point_set_is_reported(captured):
    sets = toy_hierarchy()
    sets[3] = type(sets[3])("broken", 1, (0, 99))
    with pytest.raises(ValueError, match="broken"):
        fit_hierarchical_pca(toy_neutral(), captured, sets)
