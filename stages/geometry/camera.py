"""The pinhole camera of eq. 10 (Zhang et al. 2006, Sec. 12.1) and the rotation conventions, one
implementation each.

``lambda m~ = A [R | t] X~``: a head point ``X`` (mm, head frame) is seen at pixel ``m`` through
the rotation ``R`` (head -> camera), the translation ``t`` (mm) and the intrinsics
``A = [[fx, s, u0], [0, fy, v0], [0, 0, 1]]`` (px). The camera frame is OpenCV's: x right,
y down, z away from the camera; pixels have their origin at the centre of the top-left pixel.
A rotation vector ``w (3,)`` (rad) stands for ``R = exp([w]x)`` (Rodrigues; OpenCV's ``rvec``
and scipy's ``rotvec`` are the same convention).
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


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``[v]x (..., 3, 3)`` of vectors ``v (..., 3)``: ``[v]x u = v x u``."""
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def rotation_matrix(rvec: np.ndarray) -> np.ndarray:
    """``R = exp([w]x) (..., 3, 3)`` of rotation vectors ``rvec (..., 3)`` rad (Rodrigues' formula
    ``I + sin|w| K + (1 - cos|w|) K^2``, ``K = [w / |w|]x``; ``I + [w]x`` below 1e-12 rad)."""
    w = np.asarray(rvec, dtype=np.float64)
    angle = np.linalg.norm(w, axis=-1)[..., None, None]
    small = angle < 1e-12
    k = skew(w / np.where(small, 1.0, angle)[..., 0])
    full = np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)
    return np.where(small, np.eye(3) + skew(w), full)


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """The rotation vectors ``(..., 3)`` rad, angle in ``[0, pi]``, of rotation matrices ``R (..., 3, 3)``
    (the inverse of :func:`rotation_matrix`).

    Through the unit quaternion (Shepperd's method: the largest of ``4w^2, 4x^2, 4y^2, 4z^2`` from
    the trace and the diagonal, the others from it; the conversion SciPy's ``Rotation`` makes,
    without importing ``scipy.spatial``, half a second at a run's start), then
    ``angle = 2 atan2(|xyz|, w)`` with ``w >= 0`` and a series near 0."""
    R = np.asarray(R, dtype=np.float64)
    m = R.reshape(-1, 3, 3)
    diagonal = np.stack([m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    trace = diagonal.sum(axis=1)
    choice = np.concatenate([diagonal, trace[:, None]], axis=1).argmax(axis=1)
    quat = np.empty((len(m), 4))  # (x, y, z, w)
    w_largest = choice == 3
    quat[w_largest] = np.stack([m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1], 1.0 + trace], axis=1)[
        w_largest
    ]
    for i in range(3):
        rows = choice == i
        j, k = (i + 1) % 3, (i + 2) % 3
        q = np.empty((int(rows.sum()), 4))
        q[:, i] = 1.0 - trace[rows] + 2.0 * m[rows, i, i]
        q[:, j] = m[rows, j, i] + m[rows, i, j]
        q[:, k] = m[rows, k, i] + m[rows, i, k]
        q[:, 3] = m[rows, k, j] - m[rows, j, k]
        quat[rows] = q
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    quat[quat[:, 3] < 0] *= -1.0
    sin_half = np.linalg.norm(quat[:, :3], axis=1)
    angle = 2.0 * np.arctan2(sin_half, quat[:, 3])
    small = angle <= 1e-3
    scale = np.where(small, 2.0 + angle**2 / 12.0 + 7.0 * angle**4 / 2880.0, angle / np.sin(np.where(small, 1.0, angle) / 2.0))
    return (scale[:, None] * quat[:, :3]).reshape(R.shape[:-2] + (3,))
