"""Motion propagation (Sec. 10.1) against ground truth built by construction and against a flat-PCA
least-squares solution computed independently with numpy.linalg.lstsq."""

import numpy as np
import pytest

from stages.propagation.hierarchical_pca import fit_hierarchical_pca
from stages.propagation import propagate
from stages.propagation.propagate import motion_propagation, propagate_edit, start_sets, traversal_order
from tests.stages.propagation.toy_face import (
    N_POINTS,
    NOSE_TIP,
    REGIONS,
    ToySet,
    expressions,
    low_rank_modes,
    region_modes,
    toy_hierarchy,
    toy_neutral,
)


def low_rank_model(rank: int = 5):
    modes = low_rank_modes(rank, seed=11)
    captured = toy_neutral() + expressions(modes, 35, seed=12)
    return fit_hierarchical_pca(toy_neutral(), captured, toy_hierarchy(), n_components=8), modes


def test_traversal_visits_h_minus_1_then_h_plus_1_once_each():
    model, _ = low_rank_model()
    # worked by hand from toy_hierarchy(), depth first: face(0) -> left_eye(1) -> left_eye_a(5)
    # -> mouth(4) through bridge point 0 -> mouth_a(11) -> nose(3) through point 18 -> nose_a(9)
    # -> right_eye(2) through point 12 -> right_eye_a(7), right_eye_b(8); back up: nose_b(10),
    # mouth_b(12), left_eye_b(6)
    assert traversal_order(model, 0) == (0, 1, 5, 4, 11, 3, 9, 2, 7, 8, 10, 12, 6)
    assert traversal_order(model, 12) == (12, 4, 0, 1, 5, 6, 7, 2, 8, 9, 3, 10, 11)


def test_start_set_is_the_lowest_hierarchy_meeting_the_inputs():
    sets = toy_hierarchy()
    sets[0] = ToySet("eyes_only", 0, tuple(range(12)))  # level 0 no longer covers the mouth
    modes = low_rank_modes(5, seed=11)
    model = fit_hierarchical_pca(toy_neutral(), toy_neutral() + expressions(modes, 35, seed=12), sets)
    known = np.zeros((4, N_POINTS), dtype=bool)
    known[0, 20] = True  # only the mouth set (level 1) contains point 20
    known[1, 18] = True  # nose (level 1, bridge point 18) comes before mouth in layout order
    known[2, [3, 20]] = True  # level 0 contains point 3
    np.testing.assert_array_equal(start_sets(model, known), [4, 3, 0, -1])


def test_expression_in_pca_span_is_recovered_from_a_subset():
    model, modes = low_rank_model(rank=5)
    truth = expressions(modes, 6, seed=13)
    known = np.zeros((6, N_POINTS), dtype=bool)
    known[:, [1, 4, 8, 13, 16, 19, 22]] = True  # 7 points: 14 coordinates for 5 unknowns
    result = motion_propagation(model, truth, known, stop_progress_px=1e-11, max_iterations=5000)
    assert (result.iterations < 5000).all()
    np.testing.assert_allclose(result.displacements, truth, atol=1e-6)
    assert (result.input_error_px < 1e-6).all()


def test_single_global_set_converges_to_flat_pca_least_squares():
    rng = np.random.default_rng(21)
    modes = low_rank_modes(10, seed=20)
    captured = toy_neutral() + expressions(modes, 35, seed=22) + rng.normal(scale=0.5, size=(35, N_POINTS, 2))
    model = fit_hierarchical_pca(toy_neutral(), captured, [ToySet("face", 0, tuple(range(N_POINTS)))], n_components=6)
    target = expressions(modes, 3, seed=23) + rng.normal(scale=0.5, size=(3, N_POINTS, 2))  # off the subspace
    known = np.zeros((3, N_POINTS), dtype=bool)
    known[:, [0, 3, 7, 10, 13, 15, 19, 21, 23]] = True
    result = motion_propagation(model, target, known, stop_progress_px=1e-13, max_iterations=20000)

    # independent flat PCA: eigenvectors of the covariance, least squares on the known coordinates
    x = (captured - toy_neutral()).reshape(35, -1)
    mean = x.mean(axis=0)
    _, eigvec = np.linalg.eigh(np.cov(x, rowvar=False))
    basis = eigvec[:, ::-1][:, :6]
    for t in range(3):
        rows = np.repeat(known[t], 2)
        coef, *_ = np.linalg.lstsq(basis[rows], target[t].reshape(-1)[rows] - mean[rows], rcond=None)
        fit = (mean + basis @ coef).reshape(N_POINTS, 2)
        np.testing.assert_allclose(result.displacements[t][~known[t]], fit[~known[t]], atol=1e-6)
        np.testing.assert_allclose(result.displacements[t][known[t]], target[t][known[t]])
        residual = np.linalg.norm(fit[known[t]] - target[t][known[t]], axis=1).mean()
        assert result.input_error_px[t] == pytest.approx(residual, abs=1e-6)


def test_masked_points_are_ignored():
    model, modes = low_rank_model()
    truth = expressions(modes, 4, seed=31)
    known = np.random.default_rng(32).random((4, N_POINTS)) < 0.4
    garbage = truth.copy()
    garbage[~known] = np.nan
    garbage[~known & (np.arange(N_POINTS) % 2 == 0)] = 1e6
    clean = motion_propagation(model, np.where(known[..., None], truth, 0.0), known)
    dirty = motion_propagation(model, garbage, known)
    np.testing.assert_array_equal(dirty.displacements, clean.displacements)
    np.testing.assert_array_equal(dirty.iterations, clean.iterations)


def test_batched_equals_per_frame_with_mixed_masks(monkeypatch):
    monkeypatch.setattr(propagate, "_READOUT_FRAMES", 7)  # read the shared-mask frames out in slices
    sets = toy_hierarchy()
    sets[0] = ToySet("eyes_only", 0, tuple(range(12)))  # so that frames start from different sets
    modes = low_rank_modes(9, seed=41)
    rng = np.random.default_rng(42)
    captured = toy_neutral() + expressions(modes, 35, seed=43) + rng.normal(scale=0.3, size=(35, N_POINTS, 2))
    model = fit_hierarchical_pca(toy_neutral(), captured, sets, n_components=5)
    n_frames = 42
    truth = expressions(modes, n_frames, seed=44) + rng.normal(scale=0.5, size=(n_frames, N_POINTS, 2))
    known = rng.random((n_frames, N_POINTS)) < 0.3  # frames 0-11: a mask of their own
    known[0] = False
    known[1, :] = False
    known[1, 20] = True
    known[12:] = False
    known[12:, [2, 9, 15, 21]] = True  # frames 12-41 share one mask of 4 points (>= 2 * 4 + 1 frames)
    options = {"record_history": True, "max_iterations": 150, "stop_progress_px": 0.005}
    batched = motion_propagation(model, truth, known, **options)
    assert len(set(start_sets(model, known).tolist())) >= 3
    assert len(set(batched.iterations[12:].tolist())) >= 3  # frames stop at different iterations
    assert len(set((batched.iterations[12:] // 16).tolist())) >= 2  # stops in different basis blocks
    assert 0 < (batched.iterations[12:] == 150).sum() < n_frames - 12  # some reach the cap
    for t in range(n_frames):
        single = motion_propagation(model, truth[t : t + 1], known[t : t + 1], **options)
        np.testing.assert_allclose(batched.displacements[t], single.displacements[0], atol=1e-8)
        assert batched.iterations[t] == single.iterations[0]
        np.testing.assert_allclose(batched.input_error_px[t], single.input_error_px[0], atol=1e-8)
        np.testing.assert_allclose(batched.error_history_px[t], single.error_history_px[0], atol=1e-8, equal_nan=True)
    assert batched.iterations[0] == 0 and np.isnan(batched.input_error_px[0])
    assert not batched.displacements[0].any()


def test_stop_criterion_and_history():
    model, modes = low_rank_model(rank=8)
    truth = expressions(modes, 2, seed=51) + np.random.default_rng(52).normal(scale=1.0, size=(2, N_POINTS, 2))
    known = np.zeros((2, N_POINTS), dtype=bool)
    known[:, ::3] = True
    loose = motion_propagation(model, truth, known, stop_progress_px=0.05, record_history=True)
    tight = motion_propagation(model, truth, known, stop_progress_px=1e-5, max_iterations=5000, record_history=True)
    assert (loose.iterations < tight.iterations).all()
    capped = motion_propagation(model, truth, known, stop_progress_px=0.0, max_iterations=7, record_history=True)
    assert (capped.iterations == 7).all() and not np.isnan(capped.error_history_px).any()
    for r in (loose, tight):
        last = r.error_history_px[np.arange(2), r.iterations - 1]
        np.testing.assert_allclose(last, r.input_error_px)
        assert r.iterations.max() < r.error_history_px.shape[1]
        assert np.isnan(r.error_history_px[np.arange(2), r.iterations]).all()
        assert (r.error_history_px[:, 0] > r.input_error_px).all()  # the error falls


def test_dragging_the_nose_tip_moves_the_nose_region():
    rng = np.random.default_rng(61)
    captured = toy_neutral() + expressions(region_modes(), 40, seed=62) + rng.normal(scale=0.1, size=(40, N_POINTS, 2))
    model = fit_hierarchical_pca(toy_neutral(), captured, toy_hierarchy(), n_components=8)
    start = toy_neutral()
    held = propagate_edit(model, start, {NOSE_TIP: start[NOSE_TIP]}, stop_progress_px=1e-9)
    dragged = propagate_edit(model, start, {NOSE_TIP: start[NOSE_TIP] + [0.0, 6.0]}, stop_progress_px=1e-9)
    np.testing.assert_allclose(dragged[NOSE_TIP], start[NOSE_TIP] + [0.0, 6.0])
    moved = dragged - held
    nose = [i for i in REGIONS["nose"] if i != NOSE_TIP]
    far = list(REGIONS["left_eye"]) + list(REGIONS["right_eye"])
    np.testing.assert_allclose(moved[nose], np.tile([0.0, 6.0], (len(nose), 1)), atol=0.3)
    assert np.abs(moved[far]).max() < 0.3
    # the mask form holds the points of the current geometry where they are
    mask = np.zeros(N_POINTS, dtype=bool)
    mask[NOSE_TIP] = True
    moved_geometry = start.copy()
    moved_geometry[NOSE_TIP] += [0.0, 6.0]
    np.testing.assert_allclose(propagate_edit(model, moved_geometry, mask, stop_progress_px=1e-9), dragged)
