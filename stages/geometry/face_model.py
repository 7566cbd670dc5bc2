"""A 3D shape model of the tracked points that the tracker fits every frame (head pose and
expression jointly; an extension beyond the paper's purely 2D tracking, Sec. 14.1).

The model of N points is ``X(c) = X0 + B c`` in the head frame (mm), seen through the head pose
``(R, t)`` and the intrinsics ``A`` of eq. 10: ``x_i = pi(A (R X_i(c) + t))``.

- ``X0 (N, 3)``: the pack's generic 3D model adapted to the clip's first frame, taken as the
  frontal neutral (:func:`stages.geometry.pose.adapt_model`): each point keeps the generic depth
  and moves parallel to the image plane onto its first-frame position.
- ``B (N, 3, M)``: the first ``M`` principal components of the performer pack's captured
  geometries (the 30-40 expressions of Sec. 10/14, frontal, px) lifted to 3D the same way: each
  captured displacement, carried into clip pixels by the 2D similarity (eq. 8-9) between the
  pack's neutral and the first frame, moves the point parallel to the image plane at its generic
  depth. ``scale (M,)`` is each component's standard deviation over the captured set, mm.

:func:`fit_face_model` solves ``(R, t, c)`` for one frame by Gauss-Newton on the
information-weighted reprojection error, Huber-robust, with a Gaussian prior on ``c`` (the
captured set's spread). The fitted model's projection tells the tracker where a point with a
weak or ambiguous template (the textureless nose tip, the hairline along its edge) must be, and
its pose is the head pose that ``pose.pnp`` then recovers from the rigid points.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from stages.actor_pack import ActorPack
from stages.geometry.camera import project
from stages.geometry.rotation import rotation_rodrigues, skew
from stages.geometry.similarity import fit_similarity
from stages.geometry.frontalize import adapt_to_reference, frontal_translation
from stages.pack.bundles import geometry_from_bundle, geometry_to_bundle, model3d_from_bundle, model3d_to_bundle


@dataclass(frozen=True)
class FaceModel:
    """``X(c) = neutral + basis @ c`` (head frame, mm) seen through ``camera``.

    Attributes
    ----------
    neutral : (N, 3) float64
        The points at the neutral expression, head frame (mm); the first frame is at ``R = I``,
        ``t = t0``.
    basis : (N, 3, M) float64
        Orthonormal expression components (each ``(N*3,)`` column has unit norm).
    scale : (M,) float64
        Standard deviation of each component's coefficient over the captured set, mm.
    t0 : (3,) float64
        Head translation of the first frame, mm.
    camera : (3, 3) float64
        Intrinsic matrix ``A``.
    """

    neutral: np.ndarray
    basis: np.ndarray
    scale: np.ndarray
    t0: np.ndarray
    camera: np.ndarray

    def project(self, R: np.ndarray, t: np.ndarray, c: np.ndarray) -> np.ndarray:
        """Image positions ``(N, 2)`` px of the model with coefficients ``c (M,)`` at pose ``R (3, 3)``,
        ``t (3,)`` mm (eq. 10)."""
        return project((self.neutral + self.basis @ c) @ R.T + t, self.camera)[0]

    def first_frame_fit(self) -> "FaceFit":
        """The fit of the first frame: frontal (``R = I``), ``t0``, neutral expression (``c = 0``)."""
        c = np.zeros(self.basis.shape[2])
        return FaceFit(np.eye(3), self.t0.copy(), c, self.project(np.eye(3), self.t0, c))


def build_face_model(
    generic: np.ndarray,
    first_xy: np.ndarray,
    rigid: np.ndarray,
    camera: np.ndarray,
    pack_neutral: np.ndarray,
    captured: np.ndarray,
    *,
    components: int = 8,
) -> FaceModel:
    """The face model of N tracked points.

    Parameters
    ----------
    generic : (N, 3) float
        The pack's generic model at the tracked points, head frame (mm).
    first_xy : (N, 2) float
        The points in the clip's first frame (frontal neutral), px.
    rigid : (R,) int
        Columns of the rigid points, which fix the first frame's translation ``t0``.
    camera : (3, 3) float
        Intrinsic matrix ``A`` of the clip.
    pack_neutral : (N, 2) float
        The points on the performer pack's neutral image, px.
    captured : (K, N, 2) float
        The pack's captured geometries, px.
    components : int
        Expression components kept, ``M <= K``.
    """
    generic = np.asarray(generic, dtype=np.float64)
    first_xy = np.asarray(first_xy, dtype=np.float64)
    t0 = frontal_translation(generic[rigid], first_xy[rigid], camera)
    neutral = adapt_to_reference(generic, first_xy, np.eye(3), t0, camera)
    a, b = fit_similarity(pack_neutral[rigid], first_xy[rigid])[:2]
    linear = np.array([[a, -b], [b, a]])
    displacement = (np.asarray(captured, dtype=np.float64) - pack_neutral) @ linear.T  # (K, N, 2) clip px
    lifted = np.stack([adapt_to_reference(generic, first_xy + d, np.eye(3), t0, camera) for d in displacement])
    delta = (lifted - neutral).reshape(len(lifted), -1)
    _, singular, rows = np.linalg.svd(delta, full_matrices=False)
    m = int(min(components, len(rows)))
    basis = rows[:m].T.reshape(len(generic), 3, m)
    return FaceModel(neutral, basis, singular[:m] / np.sqrt(len(delta)), t0, np.asarray(camera, dtype=np.float64))


def bundle_face_model(
    model3d: Mapping[str, np.ndarray],
    geometry: Mapping[str, np.ndarray],
    names: Sequence[str],
    first_xy: np.ndarray,
    rigid: np.ndarray,
    camera: np.ndarray,
    *,
    components: int = 8,
) -> FaceModel:
    """:func:`build_face_model` of the points ``names`` from ``pack.load``'s ``pack_model3d`` and
    ``pack_geometry`` bundles (the generic model, the neutral and the captured geometries at those
    points); ValueError naming a point the pack does not have."""
    generic = model3d_from_bundle(model3d, names)
    pack = geometry_from_bundle(geometry)
    rows = pack.rows(names)
    return build_face_model(generic, first_xy, rigid, camera, pack.neutral[rows], pack.captured[:, rows], components=components)


def pack_face_model(
    pack: ActorPack, names: Sequence[str], first_xy: np.ndarray, rigid: np.ndarray, camera: np.ndarray, *, components: int = 8
) -> FaceModel:
    """:func:`bundle_face_model` of a loaded actor pack (scripts use the library directly)."""
    return bundle_face_model(
        model3d_to_bundle(pack), geometry_to_bundle(pack), names, first_xy, rigid, camera, components=components
    )


@dataclass
class FaceFit:
    """One frame's fit: rotation ``R (3, 3)``, translation ``t (3,)`` mm, coefficients ``c (M,)``
    and the model's projection ``xy (N, 2)`` px."""

    R: np.ndarray
    t: np.ndarray
    c: np.ndarray
    xy: np.ndarray


def fit_face_model(
    model: FaceModel,
    observed: np.ndarray,
    information: np.ndarray,
    start: FaceFit,
    *,
    ridge: float = 1.0,
    huber_px: float = 1.0,
    iterations: int = 3,
) -> FaceFit:
    """Pose and expression of one frame: Gauss-Newton on

    ``sum_i rho(r_i^T W_i r_i) + ridge * |c / scale|^2``,  ``r_i = pi(A (R X_i(c) + t)) - m_i``

    with ``W_i (2, 2)`` the information of observation ``m_i`` (zero for a point not to use) and
    ``rho`` Huber on the Mahalanobis length at ``huber_px`` (reweighted each iteration). The
    rotation is updated on the left, ``R <- exp([w]x) R``.

    Parameters
    ----------
    model : FaceModel
    observed : (N, 2) float
        Measured positions, px.
    information : (N, 2, 2) float
        Their weights, 1/px^2 (a tracker's template information, normalized).
    start : FaceFit
        Initial guess (the previous frame's fit, or its extrapolation).

    Returns
    -------
    FaceFit
    """
    R, t, c = start.R.copy(), start.t.copy(), start.c.copy()
    fx, fy = model.camera[0, 0], model.camera[1, 1]
    m = len(c)
    prior = ridge / np.maximum(model.scale, 1e-9) ** 2
    for _ in range(iterations):
        rotated = (model.neutral + model.basis @ c) @ R.T  # (N, 3) R X_i
        x, y, z = (rotated + t).T
        residual = project(rotated + t, model.camera)[0] - observed
        d_proj = np.zeros((len(z), 2, 3))  # d pi / d camera_xyz
        d_proj[:, 0, 0], d_proj[:, 0, 2] = fx / z, -fx * x / z**2
        d_proj[:, 1, 1], d_proj[:, 1, 2] = fy / z, -fy * y / z**2
        jac = np.concatenate([d_proj @ -skew(rotated), d_proj, d_proj @ (R[None] @ model.basis)], axis=2)  # (N, 2, 6 + M)
        length = np.sqrt(np.maximum(((information @ residual[:, :, None])[:, :, 0] * residual).sum(axis=1), 0.0))
        weight = np.minimum(1.0, huber_px / np.maximum(length, 1e-12))[:, None, None] * information
        flat = jac.reshape(-1, 6 + m)
        weighted = (weight @ jac).reshape(-1, 6 + m)  # (2N, P)
        normal = flat.T @ weighted
        gradient = weighted.T @ residual.ravel()
        normal[6:, 6:] += np.diag(prior)
        gradient[6:] += prior * c
        step = np.linalg.solve(normal + 1e-9 * np.eye(6 + m), -gradient)
        R = rotation_rodrigues(step[:3]) @ R
        t = t + step[3:6]
        c = c + step[6:]
    return FaceFit(R, t, c, model.project(R, t, c))
