"""The performer's head pose carried onto the target's 3D model (Sec. 14.1).

The performer's pose per frame is a weak-perspective 3D similarity relative to the reference
(neutral) frame, in the performer's camera frame (``compensate.rigid3d``: ``X(t) = s R X(r) +
t``, px; x right, y down, z away). On the target it becomes a rigid motion of the target mesh in
the target camera's frame (mm):

    X' = R R_ref (X - P) + P'

with the same rotation ``R`` (composed with ``R_ref``, the performer's own rotation at the
reference frame when it is known, since the pack's target is frontal) about the target's pivot ``P`` (its head centre). The pivot moves as
the performer's face centre does: the centre's image displacement ``delta = (s R c + t - c)_xy``
(px, ``c`` the performer's face centre at depth 0) is scaled by the face-size ratio (target px /
performer px) and added to the pivot's projection, and the pivot's depth becomes ``P_z / s`` (a
face ``s`` times larger in the image is ``s`` times nearer). ``P'`` is that pixel back-projected at
that depth (eq. 10 inverted).
"""

from __future__ import annotations

import numpy as np

from stages.mesh3d.model import lift

__all__ = ["head_motion_3d", "apply_head"]


def head_motion_3d(
    R: np.ndarray,
    tvec: np.ndarray,
    scale: np.ndarray,
    *,
    source_center: np.ndarray,
    pivot: np.ndarray,
    A: np.ndarray,
    size_ratio: float,
    reference: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Rigid motion of the target mesh per frame from the performer's relative head pose.

    Parameters
    ----------
    R : (T, 3, 3) float
        Performer's rotation relative to the reference frame (camera frame axes).
    tvec : (T, 3) float
        Translation of the weak-perspective similarity, performer px.
    scale : (T,) float
        Its scale ``s`` (> 0).
    source_center : (2,) float
        The performer's face centre in the reference frame, px.
    pivot : (3,) float
        The target's head centre ``P``, target camera frame, mm.
    A : (3, 3) float
        Target intrinsics, px.
    size_ratio : float
        Target face size / performer face size (px / px).
    reference : (3, 3) float, optional
        The performer's own head rotation at the reference frame (identity: the reference is
        frontal); the mesh turns by ``R reference`` about ``P`` (the pack's target is frontal),
        while ``P'`` follows the performer's relative motion.

    Returns
    -------
    rotation : (T, 3, 3) float64
    translation : (T, 3) float64, mm
        ``X' = rotation X + translation`` (= ``R reference (X - P) + P'``).
    """
    R = np.asarray(R, np.float64)
    tvec = np.asarray(tvec, np.float64)
    scale = np.asarray(scale, np.float64)
    T = len(R)
    if R.shape != (T, 3, 3) or tvec.shape != (T, 3) or scale.shape != (T,):
        raise ValueError(f"expected R (T, 3, 3), tvec (T, 3), scale (T,); got {R.shape}, {tvec.shape}, {scale.shape}")
    if not np.all(scale > 0):
        raise ValueError("scale must be > 0 in every frame")
    P = np.asarray(pivot, np.float64)
    A = np.asarray(A, np.float64)
    c = np.array([*np.asarray(source_center, np.float64), 0.0])
    moved = scale[:, None] * np.einsum("tij,j->ti", R, c) + tvec
    delta = (moved - c)[:, :2]
    p0 = A @ P
    u0 = p0[:2] / p0[2]
    P_new = lift((u0 + size_ratio * delta)[:, None, :], (P[2] / scale)[:, None], A)[:, 0]
    rotation = R @ (np.eye(3) if reference is None else np.asarray(reference, np.float64))
    return rotation, P_new - np.einsum("tij,j->ti", rotation, P)


def apply_head(vertices: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """``X' = rotation X + translation`` for vertices ``(T, V, 3)`` (or ``(V, 3)`` with ``(3, 3)``, ``(3,)``), mm."""
    return np.einsum("...ij,...vj->...vi", rotation, vertices) + np.asarray(translation)[..., None, :]
