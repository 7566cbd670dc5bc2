"""The target's 3D model: feature points lifted to 3D, a triangle mesh over them, 3D examples.

Where the depth comes from
--------------------------
An actor pack holds 2D feature points of every example (all taken at one frontal pose), the
camera matrix ``A`` of eq. 10 and a *generic* 3D face model (mean shape, head frame, mm) — the
model of Sec. 12.1. The generic model is posed on the pack's neutral points by PnP (eq. 10-11,
``cv2.solvePnP``); the camera depth ``z_i`` of each posed model point is taken as the target's
depth of point ``i``, and every 2D point is back-projected at that depth:

    X_i = z_i A^-1 (u_i, v_i, 1)^T                                 (eq. 10 inverted)

so each lifted point reprojects exactly onto its 2D position. The same per-point depth is used
for every example (the pack has no depth of its own): expression-dependent depth (a jaw drop
moving the chin back) is not recovered. How wrong that is is measured on the fixtures, where the
generator knows the truth (``scripts/bench_render3d.py``, docs/render3d.md).

Camera frame (the pack camera's): x right, y down, z away from the camera, mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.actor_pack import ActorPack
from stages.layout import Layout
from stages.pack.bundles import PackImages
from stages.synthesis.warp import triangulate

__all__ = [
    "TargetModel",
    "fit_generic_depth",
    "lift",
    "skin_points",
    "target_depth",
    "skin_triangles",
    "build_target_model",
    "face_subregions",
]


@dataclass(frozen=True)
class TargetModel:
    """The target face in 3D, in the pack camera's frame (mm).

    ``names (N,)`` layout point names; ``camera (3, 3)`` intrinsics A (px); ``size`` (W, H) px;
    ``depth (N,)`` camera depth of each point (mm, from the posed generic model); ``neutral (N, 3)``
    and ``examples (M, N, 3)`` lifted geometries (mm); ``example_names (M,)``;
    ``triangles (F, 3)`` mesh over the skin points (teeth points are vertices of no triangle),
    counter-clockwise on screen; ``members (S, N)`` bool, the points of each face subregion
    (G^R of Sec. 6; the teeth subregion left out); ``head_R (3, 3)``, ``head_t (3,)`` the generic
    model's pose (head frame -> camera frame, the head origin between the eyes at ``head_t``).
    """

    names: np.ndarray
    camera: np.ndarray
    size: tuple[int, int]
    depth: np.ndarray
    neutral: np.ndarray
    examples: np.ndarray
    example_names: np.ndarray
    triangles: np.ndarray
    members: np.ndarray
    head_R: np.ndarray
    head_t: np.ndarray


def fit_generic_depth(
    model3d: np.ndarray, points: np.ndarray, A: np.ndarray, *, use: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pose the generic model on 2D points (PnP, eq. 10-11) and read each point's camera depth.

    Parameters
    ----------
    model3d : (N, 3) float
        Generic face model, head frame, mm.
    points : (N, 2) float
        The target's 2D points (px) at the pose to fit (the pack's neutral).
    A : (3, 3) float
        Intrinsics, px.
    use : (N,) bool, optional
        Points that enter the fit (default all).

    Returns
    -------
    depth : (N,) float
        Camera depth ``z`` of every posed model point, mm.
    R : (3, 3) float
    t : (3,) float
        The pose, ``X_cam = R X_head + t`` (mm).
    """
    import cv2

    model3d = np.asarray(model3d, np.float64)
    points = np.asarray(points, np.float64)
    if model3d.ndim != 2 or model3d.shape[1] != 3 or points.shape != (len(model3d), 2):
        raise ValueError(f"expected model3d (N, 3) and points (N, 2), got {model3d.shape} and {points.shape}")
    mask = np.ones(len(points), bool) if use is None else np.asarray(use, bool)
    if mask.sum() < 6:
        raise ValueError(f"PnP needs at least 6 points, got {int(mask.sum())}")
    ok, rvec, tvec = cv2.solvePnP(model3d[mask], points[mask], np.asarray(A, np.float64), None, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise ValueError("PnP of the generic model on the neutral points failed")
    R = cv2.Rodrigues(rvec)[0]
    t = tvec.reshape(3)
    return (model3d @ R.T + t)[:, 2], R, t


def lift(points: np.ndarray, depth: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Back-project 2D points at known camera depths: ``X = z A^-1 (u, v, 1)`` (eq. 10 inverted).

    Parameters
    ----------
    points : (..., N, 2) float, px
    depth : (N,) or (..., N) float, mm
    A : (3, 3) float, px

    Returns
    -------
    (..., N, 3) float64, camera frame mm; reprojects exactly onto ``points``.
    """
    points = np.asarray(points, np.float64)
    if points.shape[-1] != 2:
        raise ValueError(f"points must be (..., N, 2), got {points.shape}")
    homog = np.concatenate([points, np.ones(points.shape[:-1] + (1,))], axis=-1)
    rays = homog @ np.linalg.inv(np.asarray(A, np.float64)).T
    return rays * np.asarray(depth, np.float64)[..., None]


def skin_points(names: np.ndarray) -> np.ndarray:
    """``(N,) bool``: the layout points that are mesh vertices (all but the ``teeth_*`` points)."""
    return np.array([not str(n).startswith("teeth_") for n in names])


def target_depth(
    model3d: np.ndarray, neutral: np.ndarray, A: np.ndarray, names: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The target's depth of every layout point and its head centre, from the posed generic model.

    Parameters
    ----------
    model3d : (N, 3) float, mm, head frame: the generic model in the layout's point order
    neutral : (N, 2) float, px: the pack's neutral points
    A : (3, 3) float, px: the pack's intrinsics
    names : (N,) str: the layout's point names

    Returns
    -------
    depth : (N,) float64, mm (:func:`fit_generic_depth` on the skin points)
    pivot : (3,) float64, mm: the head centre, mean of the lifted neutral's skin points
    R, t : the generic model's pose (head frame -> camera frame)

    Raises
    ------
    ValueError
        The generic model cannot be posed on the neutral points.
    """
    skin = skin_points(names)
    depth, R, t = fit_generic_depth(model3d, neutral, A, use=skin)
    return depth, lift(neutral, depth, A)[skin].mean(0), R, t


def skin_triangles(points: np.ndarray, skin: np.ndarray) -> np.ndarray:
    """Delaunay triangles over the skin points, counter-clockwise on screen (y down).

    Parameters
    ----------
    points : (N, 2) float, px (the pack's standard geometry: mouth open, lips apart)
    skin : (N,) bool, the points that become mesh vertices

    Returns
    -------
    (F, 3) int32 layout point indices.
    """
    idx = np.flatnonzero(np.asarray(skin, bool))
    tri = idx[triangulate(np.asarray(points, np.float64)[idx])]
    p = np.asarray(points, np.float64)[tri]
    area = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 1, 1] - p[:, 0, 1]) * (p[:, 2, 0] - p[:, 0, 0])
    return np.where((area < 0)[:, None], tri[:, [0, 2, 1]], tri).astype(np.int32)


def face_subregions(layout: Layout) -> np.ndarray:
    """``(S, N)`` bool membership G^R of each face subregion (teeth subregion left out)."""
    rows = [s for s in layout.subregions if not s.teeth]
    members = np.zeros((len(rows), layout.n_points), bool)
    for k, s in enumerate(rows):
        members[k, list(s.all_points)] = True
    return members


def build_target_model(pack: ActorPack | PackImages, model3d: np.ndarray, intrinsics: np.ndarray) -> TargetModel:
    """The target's 3D model from an actor pack (depth from the posed generic model).

    Parameters
    ----------
    pack : the pack's layout, image size, neutral, standard and examples (an :class:`ActorPack`, or
        the :class:`PackImages` of ``pack.load``'s ``images`` bundle).
    model3d : (N, 3) the generic 3D model in the layout's point order, mm.
    intrinsics : (3, 3) the camera matrix A of eq. 10, px.

    Raises
    ------
    ValueError
        The generic model cannot be posed on the neutral points.
    """
    names = np.array(pack.layout.point_names)
    skin = skin_points(names)
    A = np.asarray(intrinsics, np.float64)
    depth, _, R, t = target_depth(model3d, pack.neutral.points, A, names)
    examples = lift(np.stack([e.points for e in pack.examples]), depth, A)
    return TargetModel(
        names=names,
        camera=A,
        size=tuple(int(v) for v in pack.image_size),
        depth=depth,
        neutral=lift(pack.neutral.points, depth, A),
        examples=examples,
        example_names=np.array([e.name for e in pack.examples]),
        triangles=skin_triangles(pack.standard.points, skin),
        members=face_subregions(pack.layout),
        head_R=R,
        head_t=t,
    )
