"""Motion compensation with the 3D head pose (an extension beyond the paper).

The paper removes head motion with a 2D similarity (Sec. 12, eq. 8-9), which cannot undo
out-of-plane rotation: under yaw or pitch the face foreshortens unevenly and that shows up as
false expression displacements. The paper estimates the 3D pose (Sec. 12.1, eq. 10) but uses it
only to drive the head of the result. This module uses the pose to *frontalize* the tracked
points instead: every observed point is lifted to 3D with the depth of the generic face model,
taken into the head frame, and re-projected at the neutral frame's pose.

For a frame with pose ``(R, t)`` (model -> camera, eq. 10), reference (neutral, frame 0) pose
``(R0, t0)``, intrinsics ``A`` and ``pi(X) = (X_x / X_z, X_y / X_z)``:

1. Lift (:func:`lift_to_head`): point ``i`` of the head model ``X_i`` (head frame, mm) lies at
   camera depth ``z_i = (R X_i + t)_z``. The observation ``x_i`` (px) is back-projected along its
   camera ray to that depth and moved into the head frame with the inverse pose::

       X'_i = R^T (z_i A^-1 (x_i, 1) - t)

2. Re-project at the reference pose (:func:`frontalize`)::

       x_frontal_i = pi(A (R0 X'_i + t0)) = pi(A (R0 R^T (z_i A^-1 (x_i, 1) - t) + t0))

   and the compensated displacement is ``d_i = x_frontal_i - x_neutral_i``, the 3D counterpart
   of the paper's ``T^-1(x'_i) - x_i``.

The head model ``X_i`` is the pack's generic model (mean shape) adapted to the performer's
neutral frame as ``pose.pnp`` does (:func:`stages.geometry.pose.adapt_model`): each point keeps
its depth and is moved parallel to the image plane onto its frame-0 observation. Here this is
the lift of step 1 applied to frame 0 with the pose bundle's own frame-0 pose, i.e.
``X_i = R0^T (z0_i A^-1 (x0_i, 1) - t0)`` with ``z0_i`` the generic point's depth under
``(R0, t0)``; with ``R0 = I`` it is exactly ``adapt_model``'s second step, and it puts *every*
tracked point (not only the rigid ones PnP uses) in the head frame the poses refer to. So frame 0
gives ``d = 0`` exactly, and a rigid head with an exact pose gives ``d = 0`` in every frame.

The only approximation is the depth: a non-rigid deformation ``delta_i`` changes the true depth
by ``(R delta_i)_z`` (and the generic model differs from the performer), which the lift cannot
see. The point then slides along its ray, and the error after re-projection grows with that depth
error times the sine of the rotation between the frame's and the reference view (zero when the
head has not rotated; then the method reduces to a perspective-exact translation/scale removal).

Frames whose pose was not solved (``pose.valid`` False: interpolated by ``pose.pnp``) and points
whose lift lands behind either camera are flagged invalid rather than compensated another way;
motion propagation (Sec. 10) then infers those points from the others.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from runner.stage import Context, SequenceStage, StageError
from stages.geometry.bundles import DISPLACEMENTS, HEAD_POSE_PNP, POINTS
from stages.pack.bundle_types import PACK_MODEL3D
from stages.geometry.camera import project_pose
from stages.pack.bundles import model3d_from_bundle


def lift_to_head(
    xy: np.ndarray, model: np.ndarray, R: np.ndarray, t: np.ndarray, camera: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Observed points lifted to 3D at the model's depth and taken into the head frame (step 1).

    ``X'_i = R^T (z_i A^-1 (x_i, 1) - t)`` with ``z_i = (R X_i + t)_z``.

    Parameters
    ----------
    xy : (..., N, 2) float
        Observed points, px.
    model : (..., N, 3) float
        The head model points giving the depths, head frame (mm); broadcast against ``xy``.
    R : (..., 3, 3) float
        Head rotation (model -> camera) per leading index.
    t : (..., 3) float
        Head translation, mm.
    camera : (3, 3) float
        Intrinsic matrix ``A`` of eq. 10.

    Returns
    -------
    points : (..., N, 3) float64
        The lifted points in the head frame, mm.
    in_front : (..., N) bool
        The model depth ``z_i`` is positive (the lift is meaningful).
    """
    xy = np.asarray(xy, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    depth = np.einsum("...j,...nj->...n", R[..., 2, :], np.asarray(model, dtype=np.float64)) + t[..., None, 2]
    rays = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1) @ np.linalg.inv(camera).T
    camera_points = depth[..., None] * rays
    head = np.einsum("...ji,...nj->...ni", R, camera_points - t[..., None, :])
    return head, depth > 0


def frontalize(
    xy: np.ndarray, model: np.ndarray, R: np.ndarray, t: np.ndarray, camera: np.ndarray, *, reference: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Tracked points with the head motion removed by the 3D pose (module docstring, steps 1-2).

    Parameters
    ----------
    xy : (T, N, 2) float
        Observed points per frame, px.
    model : (N, 3) or (T, N, 3) float
        Head model points giving the depths, head frame (mm), in the frame the poses refer to
        (for the stage: the generic model adapted by :func:`adapt_to_reference`).
    R : (T, 3, 3) float
        Head rotation per frame (model -> camera).
    t : (T, 3) float
        Head translation per frame, mm.
    camera : (3, 3) float
        Intrinsic matrix ``A``.
    reference : int
        Frame whose pose ``(R0, t0)`` the points are re-projected with (the neutral frame).

    Returns
    -------
    frontal : (T, N, 2) float64
        ``pi(A (R0 R^T (z A^-1 (x, 1) - t) + t0))`` px; NaN where not ``ok``.
    ok : (T, N) bool
        The lift and the re-projection are both in front of the camera.
    """
    head, in_front = lift_to_head(xy, np.broadcast_to(model, np.shape(xy)[:-1] + (3,)), R, t, camera)
    frontal, ahead = project_pose(head, np.asarray(R[reference]), np.asarray(t[reference]), camera)
    ok = in_front & ahead
    return np.where(ok[..., None], frontal, np.nan), ok


def adapt_to_reference(model: np.ndarray, xy: np.ndarray, R: np.ndarray, t: np.ndarray, camera: np.ndarray) -> np.ndarray:
    """The generic model adapted to the neutral frame under that frame's pose.

    Each point keeps its depth under ``(R, t)`` and moves parallel to the image plane onto its
    observation: :func:`lift_to_head` of the neutral observations with the generic model's
    depths. :func:`stages.geometry.pose.adapt_model` is this with ``R = I`` and a translation it
    solves itself for the rigid points.

    Parameters
    ----------
    model : (N, 3) float
        Generic model points, head frame (mm).
    xy : (N, 2) float
        Their observations in the neutral frame, px.
    R, t : (3, 3), (3,) float
        The neutral frame's pose.
    camera : (3, 3) float
        Intrinsic matrix ``A``.

    Returns
    -------
    (N, 3) float64
        The adapted model, head frame (mm).
    """
    return lift_to_head(xy, model, R, t, camera)[0]


def frontal_translation(model: np.ndarray, image: np.ndarray, camera: np.ndarray) -> np.ndarray:
    """The head translation ``t (3,)`` (model units) of a frame taken as frontal (``R = I``): the
    ``t`` minimizing the algebraic error of eq. 10, ``(u - u0)(z + tz) = alpha (x + tx)`` and the
    same in y, over the points ``model (n, 3)`` observed at ``image (n, 2)`` px with ``camera``."""
    fx, fy, u0, v0 = camera[0, 0], camera[1, 1], camera[0, 2], camera[1, 2]
    du, dv = image[:, 0] - u0, image[:, 1] - v0
    n = len(model)
    system = np.zeros((2 * n, 3))
    system[:n, 0], system[:n, 2] = fx, -du
    system[n:, 1], system[n:, 2] = fy, -dv
    rhs = np.concatenate([du * model[:, 2] - fx * model[:, 0], dv * model[:, 2] - fy * model[:, 1]])
    return np.linalg.lstsq(system, rhs, rcond=None)[0]


class PoseCompensate(SequenceStage):
    """``compensate.pose3d``: head motion removed from tracked points with the 3D pose.

    An extension beyond the paper (module docstring). Its ``displacements`` bundle has the keys of
    ``compensate.similarity``'s (``d``, ``valid``, ``names``, ``neutral`` = frame 0, and ``fps``,
    ``size`` when the points carry them), so ``map.expression`` takes either. A point is valid
    where it is valid in the frame and in frame 0, the frame's pose was solved and the lift is in
    front of the camera; elsewhere ``d`` is 0 and propagation infers the point. The intrinsics are
    the camera matrix ``pose.pnp`` solved with (the pose bundle's ``camera``).
    """

    name = "compensate.pose3d"
    version = "4"
    doc = "3D motion compensation: points lifted with the generic model and the pose, re-projected at frame 0's pose"
    inputs = {"points": POINTS, "pose": HEAD_POSE_PNP, "model3d": PACK_MODEL3D}
    outputs = {"displacements": DISPLACEMENTS}

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        points, pose = inputs["points"], inputs["pose"]
        names = np.asarray(points["names"])
        xy = np.asarray(points["xy"], dtype=np.float64)
        valid = np.asarray(points["valid"], bool)
        try:
            generic = model3d_from_bundle(inputs["model3d"], names)
        except ValueError as exc:
            raise StageError(f"{self.name}: input 'model3d': {exc} (no 3D model point)") from None
        if len(pose["R"]) != len(xy):
            raise StageError(f"{self.name}: the pose has {len(pose['R'])} frames, the points {len(xy)}")
        pose_valid = np.asarray(pose["valid"], bool)
        if not pose_valid[0]:
            raise StageError(
                f"{self.name}: the pose of frame 0 (the neutral reference) was not solved; "
                "track the rigid points in the first frame"
            )
        R, t = np.asarray(pose["R"], dtype=np.float64), np.asarray(pose["tvec"], dtype=np.float64)
        camera = np.asarray(pose["camera"], dtype=np.float64)
        model = adapt_to_reference(generic, xy[0], R[0], t[0], camera)
        frontal, ok = frontalize(xy, model, R, t, camera, reference=0)
        good = valid & valid[:1] & ok & pose_valid[:, None]
        d = np.where(good[..., None], frontal - xy[:1], 0.0)
        skipped = int((~pose_valid).sum())
        if skipped:
            ctx.log.info("%s: %d frames without a solved pose: their points are flagged invalid", self.name, skipped)
        out = {"d": d, "valid": good, "names": names, "neutral": xy[0].copy()}
        out.update({k: points[k] for k in ("fps", "size") if k in points})
        return {"displacements": out}
