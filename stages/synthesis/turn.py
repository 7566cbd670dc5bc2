"""Head turns in the 2D result: the depth-aware warp of the whole target image.

The paper carries the performer's head motion onto the output as a 2D similarity (eq. 8-9), right
for small in-plane motion; out-of-plane rotation then shows as the frontal face shifted and
turned in the image plane. Here every vertex of the warp's triangulation — the frame's feature
points and the anchors around the face (:mod:`stages.synthesis.surround`) — gets a camera depth:
the feature points the target model's depth (``render3d.head``'s ``depth``, from the pack's
generic 3D model posed on the neutral, Sec. 12.1), the anchors a depth that falls off behind the
face outline. Each vertex is lifted into the pack camera's frame, moved by the head's rigid
motion (the one the 3D render applies to the target mesh, ``X' = R X + t``, so the 2D result and
the 3D render are placed alike) weighted by how much it follows the head, and projected:

    X   = z A^-1 (u, v, 1)^T                         (eq. 10 inverted)
    X'' = w (R X + t) + (1 - w) X                    (w = 1 on the face and the head ring, 0 beyond)
    u'' = A_out X'' / z''                            (eq. 10; A_out the output size's intrinsics)

and the image is warped piecewise-affinely from the standard geometry to the projected points
(backward map, :mod:`stages.synthesis.warp`). Where the turned surface overlaps itself (the nose
over the far cheek, the face over the hair behind it) the triangles are painted far to near
(their mean depth after the motion), so the nearer surface is what shows; the triangles of the
mouth opening count :data:`MOUTH_BEHIND_MM` farther, behind the lips that close over them, and
the surround's triangles are painted before the face's: the anchors' depths are a fall-off
behind the outline, not a surface, and a ring triangle that came nearer than the cheek beside it
would paint hair over the face along its edges.
"""

from __future__ import annotations

import numpy as np

from stages.geometry.camera import project
from stages.mesh3d.model import lift

__all__ = ["MOUTH_BEHIND_MM", "turned_points", "depth_order"]

MOUTH_BEHIND_MM = 10.0


def turned_points(
    points: np.ndarray,
    depth: np.ndarray,
    weight: np.ndarray,
    A: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    *,
    A_out: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Project the triangulation's vertices after the head's motion (module docstring).

    Parameters
    ----------
    points : (B, P, 2) float, px
        Per frame the vertices before head motion (feature points, then anchors), pack image px.
    depth : (P,) float, mm
        Camera depth of each vertex before the motion.
    weight : (P,) float in [0, 1]
        How much each vertex follows the head.
    A : (3, 3) float
        The pack camera's intrinsics, px.
    R : (B, 3, 3) float
    t : (B, 3) float, mm
        The head's rigid motion per frame (target camera frame: x right, y down, z away).
    A_out : (3, 3) float, optional
        Intrinsics of the output image (another size of the same camera); ``A`` when omitted.

    Returns
    -------
    uv : (B, P, 2) float64, output px
    z : (B, P) float64, mm: camera depth after the motion
    """
    points = np.asarray(points, np.float64)
    X = lift(points, depth, A)  # (B, P, 3)
    moved = np.einsum("bij,bpj->bpi", np.asarray(R, np.float64), X) + np.asarray(t, np.float64)[:, None, :]
    w = np.asarray(weight, np.float64)[None, :, None]
    X2 = w * moved + (1.0 - w) * X
    return project(X2, A if A_out is None else A_out)[0], X2[..., 2]


def depth_order(
    triangles: np.ndarray, z: np.ndarray, *, behind: np.ndarray | None = None, under: np.ndarray | None = None
) -> np.ndarray:
    """The triangles far to near (the painter's order of the warp, whose later triangles win).

    Parameters
    ----------
    triangles : (K, 3) int
    z : (P,) float, mm: camera depth of each vertex
    behind : (K,) bool, optional
        Triangles counted :data:`MOUTH_BEHIND_MM` farther (the mouth opening).
    under : (K,) bool, optional
        Triangles painted before all the others, far to near among themselves: the surround
        (hair, ears, neck, background), which lies behind the face's outline whatever depth its
        anchors are given, so that it never paints over the face.

    Returns
    -------
    (K, 3) int32, reordered (a stable sort: equal depths keep their order).
    """
    key = np.asarray(z, np.float64)[triangles].mean(1)
    if behind is not None:
        key = key + MOUTH_BEHIND_MM * np.asarray(behind, bool)
    order = np.argsort(-key, kind="stable")
    if under is not None:
        order = order[np.argsort(~np.asarray(under, bool)[order], kind="stable")]
    return np.ascontiguousarray(triangles[order], np.int32)
