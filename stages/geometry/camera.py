"""The pinhole camera of eq. 10 (Zhang et al. 2006, Sec. 12.1), one implementation (rotations:
:mod:`stages.geometry.rotation`).

``lambda m~ = A [R | t] X~``: a head point ``X`` (mm, head frame) is seen at pixel ``m`` through
the rotation ``R`` (head -> camera), the translation ``t`` (mm) and the intrinsics
``A = [[fx, s, u0], [0, fy, v0], [0, 0, 1]]`` (px). The camera frame is OpenCV's: x right,
y down, z away from the camera; pixels have their origin at the centre of the top-left pixel.
"""

from __future__ import annotations

import numpy as np


def project(camera_xyz: np.ndarray, camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``pi(A X)`` of points ``camera_xyz (..., 3)`` in the camera frame (mm).

    Returns
    -------
    px : (..., 2) float64
        Pixel positions (inf or NaN at zero depth).
    in_front : (..., ) bool
        The depth is positive.
    """
    image = np.asarray(camera_xyz, dtype=np.float64) @ np.asarray(camera, dtype=np.float64).T
    depth = image[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return image[..., :2] / depth[..., None], depth > 0


def project_pose(points: np.ndarray, R: np.ndarray, t: np.ndarray, camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``pi(A (R X + t))`` (eq. 10) of head points ``points (..., N, 3)`` mm with one pose
    ``R (3, 3)``, ``t (3,)`` mm: pixels ``(..., N, 2)`` and ``(..., N)`` bool, True in front of
    the camera."""
    return project(np.asarray(points, dtype=np.float64) @ np.asarray(R).T + t, camera)
