"""The rotation conventions against scipy's ``Rotation`` and OpenCV's ``Rodrigues`` (independent
implementations), and the angle conventions against products of the elementary rotations."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from stages.geometry.rotation import (
    landmarker_rotation,
    rodrigues_vector,
    rotation_rodrigues,
    rotation_zyx,
    skew,
    ypr_yxz,
    ypr_zyx,
)

RNG = np.random.default_rng(11)


def test_rotation_rodrigues_is_opencvs_rodrigues():
    for w in [*RNG.normal(0.0, 1.0, (5, 3)), np.array([1e-14, 0.0, -2e-14]), np.zeros(3), np.array([0.0, np.pi, 0.0])]:
        np.testing.assert_allclose(rotation_rodrigues(w), cv2.Rodrigues(w)[0], atol=1e-12)
    batch = RNG.normal(0.0, 1.0, (2, 4, 3))
    np.testing.assert_allclose(
        rotation_rodrigues(batch), Rotation.from_rotvec(batch.reshape(-1, 3)).as_matrix().reshape(2, 4, 3, 3), atol=1e-12
    )


def test_rodrigues_vector_inverts_rotation_rodrigues():
    w = RNG.normal(0.0, 0.8, (6, 3))
    np.testing.assert_allclose(rodrigues_vector(rotation_rodrigues(w)), w, atol=1e-10)
    np.testing.assert_allclose(
        rodrigues_vector(rotation_rodrigues(w[0])), cv2.Rodrigues(rotation_rodrigues(w[0]))[0].ravel(), atol=1e-10
    )


def test_skew_is_the_cross_product():
    v, u = RNG.normal(size=(2, 3))
    np.testing.assert_allclose(skew(v) @ u, np.cross(v, u), atol=1e-14)


def test_rodrigues_vector_equals_scipys_conversion():
    """Against SciPy's ``Rotation`` (an independent implementation): random rotations, angles near
    0 and near pi, matrices a rounding error off orthogonal, any leading shape."""
    rng = np.random.default_rng(5)
    axes = rng.normal(size=(300, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    cases = [
        Rotation.random(1000, random_state=4).as_matrix(),
        Rotation.from_rotvec(axes * 1e-7).as_matrix(),
        Rotation.from_rotvec(axes * (np.pi - 1e-9)).as_matrix(),
        Rotation.random(300, random_state=6).as_matrix() + rng.normal(size=(300, 3, 3)) * 1e-13,
    ]
    for R in cases:
        np.testing.assert_allclose(rodrigues_vector(R), Rotation.from_matrix(R).as_rotvec(), rtol=0, atol=1e-12)
    R = cases[0][:6].reshape(2, 3, 3, 3)
    assert rodrigues_vector(R).shape == (2, 3, 3)
    assert rodrigues_vector(np.zeros((0, 3, 3))).shape == (0, 3)


def elementary(axis: int, degrees: float) -> np.ndarray:
    """The rotation by ``degrees`` about axis ``axis`` (0 = x, 1 = y, 2 = z), written out."""
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


YPR = np.array([[10.0, -5.0, 3.0], [-25.0, 15.0, -10.0], [0.0, 0.0, 0.0], [40.0, 30.0, 60.0]])


def test_rotation_zyx_is_rz_roll_ry_yaw_rx_pitch():
    for yaw, pitch, roll in YPR:
        expected = elementary(2, roll) @ elementary(1, yaw) @ elementary(0, pitch)
        np.testing.assert_allclose(rotation_zyx(np.array([yaw, pitch, roll])), expected, atol=1e-14)
    np.testing.assert_allclose(
        rotation_zyx(YPR), Rotation.from_euler("ZYX", YPR[:, [2, 0, 1]], degrees=True).as_matrix(), atol=1e-14
    )
    assert rotation_zyx(YPR.reshape(2, 2, 3)).shape == (2, 2, 3, 3)


def test_ypr_zyx_inverts_rotation_zyx():
    np.testing.assert_allclose(ypr_zyx(rotation_zyx(YPR)), YPR, atol=1e-9)


def test_ypr_yxz_is_the_angles_of_ry_yaw_rx_pitch_rz_roll():
    R = np.stack([elementary(1, yaw) @ elementary(0, pitch) @ elementary(2, roll) for yaw, pitch, roll in YPR])
    np.testing.assert_allclose(ypr_yxz(R), YPR, atol=1e-9)


def test_the_two_angle_conventions_differ_once_pitch_and_roll_turn():
    ypr = np.array([0.0, 15.0, 20.0])  # Rz Rx (zyx) against Rx Rz (yxz)
    assert np.abs(ypr_yxz(rotation_zyx(ypr)[None])[0] - ypr).max() > 1.0


def test_mediapipe_matrix_of_a_frontal_face_is_the_identity_and_a_turn_keeps_its_direction():
    np.testing.assert_allclose(landmarker_rotation(np.diag([2.0, 2.0, 2.0, 1.0])), np.eye(3), atol=1e-12)
    M = np.eye(4)
    M[:3, :3] = Rotation.from_euler("y", 20, degrees=True).as_matrix()  # about the vertical axis in MediaPipe's y-up frame
    nose_mp = M[:3, :3] @ np.array([0.0, 0.0, 1.0])  # MediaPipe: the nose points towards the camera (+z)
    nose = landmarker_rotation(M) @ np.array([0.0, 0.0, -1.0])  # ours: towards the camera is -z
    np.testing.assert_allclose(nose, nose_mp * np.array([1.0, -1.0, -1.0]), atol=1e-12)  # same image-x, flipped y/z axes
    assert nose[0] > 0.3


def test_landmarker_rotations_of_scaled_matrices_are_the_flipped_rotations_batched():
    R = Rotation.from_euler("yxz", RNG.uniform(-40, 40, (6, 3)), degrees=True).as_matrix()
    M = np.tile(np.eye(4), (6, 1, 1))
    M[:, :3, :3] = RNG.uniform(0.5, 3.0, (6, 1, 1)) * R  # MediaPipe's matrices carry the face's scale
    F = np.diag([1.0, -1.0, -1.0])
    out = landmarker_rotation(M)
    np.testing.assert_allclose(out, F @ R @ F, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(out), 1.0, atol=1e-12)
