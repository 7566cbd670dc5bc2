"""Rotations, one implementation per convention; each function names its convention.

Angles of a rotation vector are radians; yaw, pitch and roll are degrees, columns
``(yaw, pitch, roll)`` = rotation about Y, X and Z of the camera frame (x right, y down, z away):

- rotation vectors ``w (..., 3)``: ``R = exp([w]x)`` (Rodrigues; OpenCV's ``rvec`` and scipy's
  ``rotvec`` are the same convention): :func:`rotation_rodrigues`, :func:`rodrigues_vector`;
- ``R = Rz(roll) Ry(yaw) Rx(pitch)`` (scipy's intrinsic ``"ZYX"``; the face generator's and the
  fixtures' convention, the eigenfeature training renders'): :func:`rotation_zyx`, :func:`ypr_zyx`;
- ``R = Ry(yaw) Rx(pitch) Rz(roll)`` (scipy's intrinsic ``"YXZ"``; the head pose the stages
  report, ``ypr_deg``): :func:`ypr_yxz`;
- MediaPipe's facial transformation matrices (y up, z towards the viewer) in these axes:
  :func:`landmarker_rotation`.

The two angle conventions agree while roll is 0 and differ when roll combines with yaw or pitch.
"""

from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``[v]x (..., 3, 3)`` of vectors ``v (..., 3)``: ``[v]x u = v x u``."""
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def rotation_rodrigues(rvec: np.ndarray) -> np.ndarray:
    """``R = exp([w]x) (..., 3, 3)`` of rotation vectors ``rvec (..., 3)`` rad (Rodrigues' formula
    ``I + sin|w| K + (1 - cos|w|) K^2``, ``K = [w / |w|]x``; ``I + [w]x`` below 1e-12 rad)."""
    w = np.asarray(rvec, dtype=np.float64)
    angle = np.linalg.norm(w, axis=-1)[..., None, None]
    small = angle < 1e-12
    k = skew(w / np.where(small, 1.0, angle)[..., 0])
    full = np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)
    return np.where(small, np.eye(3) + skew(w), full)


def rodrigues_vector(R: np.ndarray) -> np.ndarray:
    """The rotation vectors ``(..., 3)`` rad, angle in ``[0, pi]``, of rotation matrices ``R (..., 3, 3)``
    (the inverse of :func:`rotation_rodrigues`).

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


def rotation_zyx(angles: np.ndarray) -> np.ndarray:
    """``R = Rz(roll) Ry(yaw) Rx(pitch)`` ``(..., 3, 3)`` of (yaw, pitch, roll) deg ``(..., 3)``,
    the inverse of :func:`ypr_zyx` (camera frame: x right, y down, z away)."""
    yaw, pitch, roll = np.moveaxis(np.radians(np.asarray(angles, dtype=np.float64)), -1, 0)
    c, s = np.cos, np.sin
    one, zero = np.ones_like(yaw), np.zeros_like(yaw)
    Rx = np.stack(
        [np.stack([one, zero, zero], -1), np.stack([zero, c(pitch), -s(pitch)], -1), np.stack([zero, s(pitch), c(pitch)], -1)], -2
    )
    Ry = np.stack(
        [np.stack([c(yaw), zero, s(yaw)], -1), np.stack([zero, one, zero], -1), np.stack([-s(yaw), zero, c(yaw)], -1)], -2
    )
    Rz = np.stack(
        [np.stack([c(roll), -s(roll), zero], -1), np.stack([s(roll), c(roll), zero], -1), np.stack([zero, zero, one], -1)], -2
    )
    return Rz @ Ry @ Rx


def ypr_zyx(R: np.ndarray) -> np.ndarray:
    """(yaw, pitch, roll) deg ``(..., 3)`` of rotations ``(..., 3, 3)`` with
    ``R = Rz(roll) Ry(yaw) Rx(pitch)`` (the generator's and the fixtures' convention)."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"expected rotations (..., 3, 3), got {R.shape}")
    yaw = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    pitch = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    roll = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.degrees(np.stack([yaw, pitch, roll], axis=-1))


def ypr_yxz(R: np.ndarray) -> np.ndarray:
    """``(T, 3, 3)`` rotations -> ``(T, 3)`` degrees (yaw, pitch, roll), ``R = Ry Rx Rz``."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_euler("YXZ", degrees=True)


def landmarker_rotation(matrix: np.ndarray) -> np.ndarray:
    """The face landmarker's head rotations in the pipeline's camera axes, ``(..., 3, 3)``.

    MediaPipe's facial transformation matrix ``(..., 4, 4)`` maps its canonical face (y up, z
    towards the camera) into its camera frame (y up, z towards the viewer); both frames are turned
    by pi about x into ours (y down, z away): ``F R F`` with ``F = diag(1, -1, -1)``. The scaled
    rotation is made orthonormal (polar decomposition, det +1). A frontal face gives the identity.
    """
    F = np.diag([1.0, -1.0, -1.0])
    u, _, vt = np.linalg.svd(np.asarray(matrix, np.float64)[..., :3, :3])
    flip = np.where(np.linalg.det(u @ vt) < 0, -1.0, 1.0)
    u = np.concatenate([u[..., :2], u[..., 2:] * flip[..., None, None]], axis=-1)
    return F @ (u @ vt) @ F
