"""2D similarity motion compensation (eq. 8-9) against known transforms and OpenCV."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from runner.stage import StageError
from stages.geometry.compensate import SimilarityCompensate, compensate
from stages.geometry.similarity import apply_similarity, fit_similarity, invert_similarity
from stages.layout import load_layout
from tests.stages.geometry.synthetic import context


def random_similarity(rng: np.random.Generator) -> np.ndarray:
    scale, angle = rng.uniform(0.8, 1.2), rng.uniform(-0.4, 0.4)
    return np.array([scale * np.cos(angle), scale * np.sin(angle), *rng.uniform(-20, 20, 2)])


def test_apply_similarity_scales_turns_and_moves():
    """(a, b) = 2 (cos 90, sin 90), t = (1, 2): (1, 0) -> 2 (0, 1) + (1, 2); any leading shape."""
    T = np.array([0.0, 2.0, 1.0, 2.0])
    np.testing.assert_allclose(apply_similarity(T, np.array([[1.0, 0.0]])), [[1.0, 4.0]], atol=1e-12)
    assert apply_similarity(T, np.zeros((3, 4, 2))).shape == (3, 4, 2)


def test_recovers_exact_similarity_and_inverts():
    rng = np.random.default_rng(0)
    src = rng.uniform(0, 200, (7, 2))
    truth = random_similarity(rng)
    np.testing.assert_allclose(fit_similarity(src, apply_similarity(truth, src)), truth, atol=1e-10)
    np.testing.assert_allclose(invert_similarity(truth, apply_similarity(truth, src)), src, atol=1e-10)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_agrees_with_opencv_least_squares(seed):
    rng = np.random.default_rng(seed)
    src = rng.uniform(0, 300, (12, 2))
    dst = apply_similarity(random_similarity(rng), src) + rng.normal(0, 1.0, src.shape)
    ours = fit_similarity(src, dst)
    # RANSAC with a threshold no point exceeds: every point an inlier, then Levenberg-Marquardt
    # refinement over all of them, i.e. the least-squares similarity of eq. 9.
    matrix, inliers = cv2.estimateAffinePartial2D(
        src, dst, method=cv2.RANSAC, ransacReprojThreshold=1e4, maxIters=50, refineIters=100
    )
    assert inliers.all()
    reference = np.array([matrix[0, 0], matrix[1, 0], matrix[0, 2], matrix[1, 2]])
    np.testing.assert_allclose(ours[:2], reference[:2], atol=1e-6)
    np.testing.assert_allclose(ours[2:], reference[2:], atol=1e-4)
    np.testing.assert_allclose(matrix[0, 1], -matrix[1, 0], atol=1e-12)


def test_robust_fit_resists_an_outlier():
    rng = np.random.default_rng(4)
    src = rng.uniform(0, 200, (10, 2))
    truth = random_similarity(rng)
    dst = apply_similarity(truth, src) + rng.normal(0, 0.2, src.shape)
    dst[3] += (25.0, -18.0)
    plain = fit_similarity(src, dst)
    robust = fit_similarity(src, dst, huber_px=1.0)
    error = lambda p: np.abs(apply_similarity(p, src) - apply_similarity(truth, src)).max()
    assert error(robust) < 0.5 < error(plain)


def synthetic_sequence(rng, n_frames=15, n_points=10, rigid=(0, 1, 2, 3, 4)):
    neutral = rng.uniform(50, 250, (n_points, 2))
    deform = rng.normal(0, 3.0, (n_frames, n_points, 2))
    deform[:, list(rigid)] = 0.0
    deform[0] = 0.0
    params = np.array([random_similarity(rng) for _ in range(n_frames)])
    params[0] = (1.0, 0.0, 0.0, 0.0)
    xy = np.stack([apply_similarity(params[t], neutral + deform[t]) for t in range(n_frames)])
    return neutral, deform, params, xy


def test_displacements_are_the_deformation_without_head_motion():
    rng = np.random.default_rng(5)
    neutral, deform, params, xy = synthetic_sequence(rng)
    valid = np.ones(xy.shape[:2], bool)
    result = compensate(xy, valid, neutral, np.arange(5))
    np.testing.assert_allclose(result["params"], params, atol=1e-9)
    np.testing.assert_allclose(result["d"], deform, atol=1e-8)
    np.testing.assert_allclose(result["residual_px"], 0.0, atol=1e-8)
    assert result["frame_valid"].all() and result["d_valid"].all()


def test_frame_with_too_few_rigid_points_is_flagged_and_interpolated():
    rng = np.random.default_rng(6)
    neutral, _, _, xy = synthetic_sequence(rng)
    valid = np.ones(xy.shape[:2], bool)
    valid[7, 1:5] = False
    result = compensate(xy, valid, neutral, np.arange(5), min_points=3)
    assert not result["frame_valid"][7] and result["frame_valid"].sum() == 14
    np.testing.assert_allclose(result["params"][7], 0.5 * (result["params"][6] + result["params"][8]))
    assert not result["d_valid"][7].any() and np.isnan(result["residual_px"][7])


def layout_bundle(rng):
    layout = load_layout("zhang134")
    names = np.array([layout.point_names[i] for i in layout.tracked])
    rigid = [list(names).index(layout.point_names[i]) for i in layout.rigid]
    neutral, deform, params, xy = synthetic_sequence(rng, n_points=len(names), rigid=rigid)
    return names, neutral, deform, params, xy


def test_stage_with_layout_and_given_neutral(tmp_path):
    rng = np.random.default_rng(7)
    names, neutral, deform, params, xy = layout_bundle(rng)
    shifted = apply_similarity(np.array([1.0, 0.0, 5.0, -3.0]), neutral)  # the neutral seen elsewhere
    points = {
        "xy": np.stack([apply_similarity(params[t], shifted + deform[t]) for t in range(len(xy))]),
        "valid": np.ones(xy.shape[:2], bool),
        "names": names,
    }
    order = np.random.default_rng(8).permutation(len(names))
    given = {"xy": shifted[None, order], "valid": np.ones((1, len(names)), bool), "names": names[order]}
    out = SimilarityCompensate().run({"points": points, "neutral": given}, {"robust": True}, context(tmp_path))
    np.testing.assert_allclose(out["displacements"]["d"], deform, atol=1e-6)
    np.testing.assert_allclose(out["displacements"]["neutral"], shifted, atol=1e-12)
    np.testing.assert_allclose(out["similarity"]["params"], params, atol=1e-6)
    assert out["similarity"]["valid"].all() and list(out["displacements"]["names"]) == list(names)


def test_stage_without_rigid_points_is_a_clear_error(tmp_path):
    points = {"xy": np.zeros((3, 2, 2)), "valid": np.ones((3, 2), bool), "names": np.array(["chin", "nose_tip"])}
    with pytest.raises(StageError, match="rigid points"):
        SimilarityCompensate().run({"points": points}, {}, context(tmp_path))
