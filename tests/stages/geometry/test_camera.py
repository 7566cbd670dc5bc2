"""The camera model and rotation conventions against OpenCV's and scipy's implementations."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from stages.geometry.camera import project, project_pose, rotation_matrix, rotation_vector, skew

RNG = np.random.default_rng(11)
CAMERA = np.array([[610.0, 0.0, 319.5], [0.0, 590.0, 239.5], [0.0, 0.0, 1.0]])


def test_rotation_matrix_is_opencvs_rodrigues():
    for w in [*RNG.normal(0.0, 1.0, (5, 3)), np.array([1e-14, 0.0, -2e-14]), np.zeros(3), np.array([0.0, np.pi, 0.0])]:
        np.testing.assert_allclose(rotation_matrix(w), cv2.Rodrigues(w)[0], atol=1e-12)
    batch = RNG.normal(0.0, 1.0, (2, 4, 3))
    np.testing.assert_allclose(
        rotation_matrix(batch), Rotation.from_rotvec(batch.reshape(-1, 3)).as_matrix().reshape(2, 4, 3, 3), atol=1e-12
    )


def test_rotation_vector_inverts_rotation_matrix():
    w = RNG.normal(0.0, 0.8, (6, 3))
    np.testing.assert_allclose(rotation_vector(rotation_matrix(w)), w, atol=1e-10)
    np.testing.assert_allclose(
        rotation_vector(rotation_matrix(w[0])), cv2.Rodrigues(rotation_matrix(w[0]))[0].ravel(), atol=1e-10
    )


def test_skew_is_the_cross_product():
    v, u = RNG.normal(size=(2, 3))
    np.testing.assert_allclose(skew(v) @ u, np.cross(v, u), atol=1e-14)


def test_projection_is_opencvs_projectpoints():
    points = RNG.uniform([-60, -80, -40], [60, 80, 40], (20, 3))
    rvec, tvec = np.array([0.1, -0.3, 0.05]), np.array([5.0, -3.0, 600.0])
    expected = cv2.projectPoints(points, rvec, tvec, CAMERA, None)[0].reshape(-1, 2)
    px, in_front = project_pose(points, rotation_matrix(rvec), tvec, CAMERA)
    np.testing.assert_allclose(px, expected, atol=1e-9)
    assert in_front.all()
    # OpenCV's model has no skew s: u = (fx x + s y) / z + u0 by hand
    skewed = CAMERA + [[0.0, 3.0, 0.0], [0, 0, 0], [0, 0, 0]]
    x, y, z = (points + tvec).T
    expected = np.stack([(610.0 * x + 3.0 * y) / z + 319.5, 590.0 * y / z + 239.5], axis=1)
    np.testing.assert_allclose(project(points + tvec, skewed)[0], expected, atol=1e-9)
    _, ahead = project(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 2.0]]), CAMERA)
    np.testing.assert_array_equal(ahead, [False, True])


def test_rotation_vector_equals_scipys_conversion():
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
        np.testing.assert_allclose(rotation_vector(R), Rotation.from_matrix(R).as_rotvec(), rtol=0, atol=1e-12)
    R = cases[0][:6].reshape(2, 3, 3, 3)
    assert rotation_vector(R).shape == (2, 3, 3)
    assert rotation_vector(np.zeros((0, 3, 3))).shape == (0, 3)
