"""compensate.rigid3d: 3D similarity compensation against known rotations (scipy as the reference)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stages.geometry.rigid3d import (choose_reference, compensate_rigid3d, euler_yaw_pitch_roll, expressiveness,
                                     head_angle_deg, similarity_3d)


def _head(n=40, seed=0):
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-60, 60, (n, 2)), rng.uniform(-30, 30, n)] + [250, 250, 500]


def test_similarity_3d_recovers_a_known_transform():
    src = _head()
    R = Rotation.from_euler("YXZ", [20, -10, 5], degrees=True).as_matrix()
    dst = 1.3 * src @ R.T + [4, -7, 11]
    s, R_est, t = similarity_3d(src, dst, np.ones(len(src)))
    assert s == pytest.approx(1.3, abs=1e-9)
    np.testing.assert_allclose(R_est, R, atol=1e-9)
    np.testing.assert_allclose(t, [4, -7, 11], atol=1e-6)


def test_compensation_undoes_head_rotation_and_keeps_expression():
    ref = _head()
    rigid = np.arange(20)
    expression = np.zeros_like(ref)
    expression[30:, 1] = 6.0  # non-rigid points move down 6 px (a mouth opening)
    angles = np.array([[0, 0, 0], [15, 5, -3], [-20, -8, 6]], float)
    frames = []
    for k, ypr in enumerate(angles):
        R = Rotation.from_euler("YXZ", ypr, degrees=True).as_matrix()
        centre = ref.mean(0)
        moved = (ref + (expression if k else 0) - centre) @ R.T + centre + [3 * k, -2 * k, 0]
        frames.append(moved)
    xyz = np.stack(frames)
    fit = compensate_rigid3d(xyz, np.ones(xyz.shape[:2], bool), 0, rigid)
    np.testing.assert_allclose(fit["d"][0], 0, atol=1e-9)
    for k in (1, 2):
        np.testing.assert_allclose(fit["d"][k], expression[:, :2], atol=1e-6)
    np.testing.assert_allclose(euler_yaw_pitch_roll(fit["R"]), angles, atol=1e-6)
    assert fit["frame_valid"].all()


def test_frames_without_rigid_points_are_held_and_flagged():
    ref = _head()
    xyz = np.stack([ref, ref + [1, 0, 0], ref + [2, 0, 0]])
    valid = np.ones(xyz.shape[:2], bool)
    valid[1, :] = False
    fit = compensate_rigid3d(xyz, valid, 0, np.arange(10))
    assert fit["frame_valid"].tolist() == [True, False, True]
    np.testing.assert_allclose(fit["t"][1], fit["t"][0])  # held from the nearest solved frame


def test_choose_reference_prefers_frontal_neutral_frames():
    names = np.array(["_neutral", "eyeLookInLeft", "jawOpen", "browInnerUp"])
    shapes = np.array([[0.9, 0.0, 0.6, 0.1],   # mouth open
                       [0.9, 0.9, 0.0, 0.0],   # gaze only: counts as neutral
                       [0.9, 0.0, 0.0, 0.05],  # neutral but turned 30 degrees
                       [0.9, 0.0, 0.0, 0.0]])  # invalid frame
    assert expressiveness(shapes, names).tolist() == pytest.approx([0.7, 0.0, 0.05, 0.0])
    matrix = np.repeat(np.eye(4)[None], 4, axis=0)
    matrix[2, :3, :3] = Rotation.from_euler("Y", 30, degrees=True).as_matrix()
    valid = np.array([True, True, True, False])
    closed = np.zeros(4)
    assert choose_reference(shapes, names, matrix, closed, valid, search_frames=10) == 1
    assert choose_reference(shapes, names, matrix, closed, valid, search_frames=1) == 0
    lips_apart = np.array([0.2, 0.2, 0.0, 0.0])  # gaps the blendshapes missed
    assert choose_reference(shapes, names, matrix, lips_apart, valid, search_frames=10) == 2
    np.testing.assert_allclose(head_angle_deg(2.0 * matrix[:, :3, :3]), [0, 0, 30, 0], atol=1e-4)
