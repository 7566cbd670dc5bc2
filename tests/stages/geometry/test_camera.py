"""The camera model against OpenCV's implementation."""

from __future__ import annotations

import cv2
import numpy as np

from stages.geometry.camera import project, project_pose
from stages.geometry.rotation import rotation_rodrigues

RNG = np.random.default_rng(11)
CAMERA = np.array([[610.0, 0.0, 319.5], [0.0, 590.0, 239.5], [0.0, 0.0, 1.0]])


def test_projection_is_opencvs_projectpoints():
    points = RNG.uniform([-60, -80, -40], [60, 80, 40], (20, 3))
    rvec, tvec = np.array([0.1, -0.3, 0.05]), np.array([5.0, -3.0, 600.0])
    expected = cv2.projectPoints(points, rvec, tvec, CAMERA, None)[0].reshape(-1, 2)
    px, in_front = project_pose(points, rotation_rodrigues(rvec), tvec, CAMERA)
    np.testing.assert_allclose(px, expected, atol=1e-9)
    assert in_front.all()
    # OpenCV's model has no skew s: u = (fx x + s y) / z + u0 by hand
    skewed = CAMERA + [[0.0, 3.0, 0.0], [0, 0, 0], [0, 0, 0]]
    x, y, z = (points + tvec).T
    expected = np.stack([(610.0 * x + 3.0 * y) / z + 319.5, 590.0 * y / z + 239.5], axis=1)
    np.testing.assert_allclose(project(points + tvec, skewed)[0], expected, atol=1e-9)
    _, ahead = project(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 2.0]]), CAMERA)
    np.testing.assert_array_equal(ahead, [False, True])
