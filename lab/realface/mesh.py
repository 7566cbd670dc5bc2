"""The 3D mesh fitted to the photo's landmarks: face, an outer ring to the image border, a mouth cavity.

Units and frames. Millimetres, scaled so the outer eye corners (landmarks 33, 263) are
:data:`EYE_CORNERS_MM` apart. Camera frame: x right, y down, z forward (OpenCV), pinhole
``A = [[f, 0, c], [0, f, c], [0, 0, 1]]`` with ``f = size`` px and ``c = (size - 1) / 2`` (pixel
origin at the centre of the top-left pixel). Landmark ``(x, y, z_px)`` of the photo is placed at
depth ``Z = Z0 + z_px * mm_per_px`` with ``Z0 = f * mm_per_px`` and back-projected through its own
pixel, ``X = (x - c) Z / f``, so the neutral mesh at the identity pose projects exactly onto the
photo's landmarks. The head frame is the camera frame moved to the head centre ``C`` (seen through the
face oval's centroid in the photo, at the nose tip's depth + :data:`HEAD_CENTRE_BEHIND_NOSE_MM`): a vertex's
head coordinates are ``X_cam - C``; a pose ``(R, t)`` maps them to ``R X + t`` (identity: ``t = C``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from matplotlib.path import Path as PolygonPath
from scipy.spatial import Delaunay

from .landmarks import FACE_OVAL, LIPS_INNER_LOWER, LIPS_INNER_UPPER, N_LANDMARKS, NOSE_TIP, OUTER_EYE_CORNERS, inner_lip_polygon

EYE_CORNERS_MM = 90.0
HEAD_CENTRE_BEHIND_NOSE_MM = 100.0
RING_SCALES = (1.3, 1.7)  # outer rings: the face oval scaled about its centroid
RING_DEPTH = (0.3, 0.6)  # their depth behind the oval, in outer-eye-corner distances
BORDER_DEPTH = 0.6  # the outermost square's depth behind the head centre, same unit
BORDER_MARGIN = 0.35  # the outermost square, this fraction of the image size beyond the border
BORDER_POINTS = 10  # per side of that square
CAVITY_DEPTH_MM = 8.0  # the mouth cavity's plane behind the inner lips' mean depth
CAVITY_GRID = (7, 6)  # cavity vertices across x and y
MOUTH_OPEN_MAX = 0.5  # the largest lip gap, in outer-eye-corner distances


def camera_matrix(size: int) -> np.ndarray:
    """The ``(3, 3)`` intrinsics of a ``size x size`` frame: ``f = size`` px, principal point at the centre."""
    c = (size - 1) / 2.0
    return np.array([[float(size), 0.0, c], [0.0, float(size), c], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class RealFaceMesh:
    """The fitted mesh (neutral, head frame).

    Attributes
    ----------
    vertices : (V, 3) float64
        Head-frame positions, mm: the 478 landmarks first, then the outer ring, then the
        mouth cavity's ``n_cavity`` vertices.
    source_px : (V, 2) float64
        Each vertex's position in the photo, px; also its texture coordinate (the skin in the
        photo, the cavity in the mouth texture, both ``size x size``).
    skin : (F, 3) int64
        Skin triangles (the Delaunay triangulation of the landmarks and the ring, without the
        triangles over the mouth opening), counter-clockwise in the photo.
    cavity : (G, 3) int64
        Mouth-cavity triangles, drawn wherever the skin leaves a hole.
    head_centre : (3,) float64
        ``C``, camera frame at the identity pose, mm.
    intrinsics : (3, 3) float64
        Camera matrix ``A``.
    mm_per_px : float
        Millimetres per photo pixel at depth ``Z0``.
    eye_px : float
        The photo's outer-eye-corner distance, px.
    size : int
        Photo and frame side, px.
    """

    vertices: np.ndarray
    source_px: np.ndarray
    skin: np.ndarray
    cavity: np.ndarray
    head_centre: np.ndarray
    intrinsics: np.ndarray
    mm_per_px: float
    eye_px: float
    size: int

    @property
    def n_cavity(self) -> int:
        return CAVITY_GRID[0] * CAVITY_GRID[1]

    @property
    def square(self) -> np.ndarray:
        """``(4 BORDER_POINTS,)`` int64: the indices of the outermost square's vertices (after the rings)."""
        stop = len(self.vertices) - self.n_cavity
        return np.arange(stop - 4 * BORDER_POINTS, stop)

    @property
    def head(self) -> np.ndarray:
        """The skin triangles of the head (the face and the two rings: hair, ears, neck), those that
        touch the outermost square left out: what turns in front of a static backdrop."""
        return self.skin[~np.isin(self.skin, self.square).any(axis=1)]


def clean_plate(photo: np.ndarray, mesh: RealFaceMesh, *, radius_px: float = 8.0) -> np.ndarray:
    """The backdrop behind the head: the photo with the head's region (the pixels the head's
    triangles cover at rest, grown by a pixel) inpainted (``cv2.inpaint``, Telea) from the pixels
    around it.

    Parameters
    ----------
    photo : (S, S, 3) uint8 RGB
    mesh : the fitted mesh (its outer ring)

    Returns
    -------
    (S, S, 3) uint8 RGB; equal to ``photo`` outside the grown region.
    """
    from .render import rasterize

    h, w = photo.shape[:2]
    mask = np.zeros(h * w, np.uint8)
    mask[rasterize(mesh.source_px, np.ones(len(mesh.source_px)), mesh.head, (h, w)).pixel] = 255
    mask = cv2.dilate(mask.reshape(h, w), np.ones((3, 3), np.uint8))
    return cv2.inpaint(np.ascontiguousarray(photo), mask, radius_px, cv2.INPAINT_TELEA)


def _back_project(px: np.ndarray, depth: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Camera-frame points ``(n, 3)`` mm of pixels ``(n, 2)`` at depths ``(n,)`` mm."""
    x = (px[:, 0] - A[0, 2]) * depth / A[0, 0]
    y = (px[:, 1] - A[1, 2]) * depth / A[1, 1]
    return np.column_stack([x, y, depth])


def _ring(landmarks_px: np.ndarray, depth: np.ndarray, centre_depth: float, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Outer-ring vertices: px ``(n, 2)`` and depth ``(n,)`` mm. Hair, neck and background lie
    behind the face (:data:`RING_DEPTH`, :data:`BORDER_DEPTH`) so that the face occludes them when
    it turns rather than folding under them."""
    oval = landmarks_px[list(FACE_OVAL)]
    oval_depth = depth[list(FACE_OVAL)]
    mid = oval.mean(axis=0)
    px, z = [], []
    for scale, behind in zip(RING_SCALES, RING_DEPTH):
        px.append(mid + scale * (oval - mid))
        z.append(oval_depth + behind * EYE_CORNERS_MM)
    lo, hi = -BORDER_MARGIN * size, (1.0 + BORDER_MARGIN) * size - 1.0
    s = np.linspace(lo, hi, BORDER_POINTS, endpoint=False)
    square = np.concatenate(
        [
            np.column_stack([s, np.full_like(s, lo)]),
            np.column_stack([np.full_like(s, hi), s]),
            np.column_stack([s[::-1] + (hi - lo) / BORDER_POINTS, np.full_like(s, hi)]),
            np.column_stack([np.full_like(s, lo), s[::-1] + (hi - lo) / BORDER_POINTS]),
        ]
    )
    px.append(square)
    z.append(np.full(len(square), centre_depth + BORDER_DEPTH * EYE_CORNERS_MM))
    return np.concatenate(px), np.concatenate(z)


def _cavity(landmarks_px: np.ndarray, depth: np.ndarray, eye_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mouth-cavity plane: a grid over the mouth opening down to the widest opening. Returns
    px ``(n, 2)``, depth ``(n,)`` mm and triangles ``(g, 3)`` (local indices)."""
    upper, lower = landmarks_px[list(LIPS_INNER_UPPER)], landmarks_px[list(LIPS_INNER_LOWER)]
    pad = 0.05 * eye_px
    x = np.linspace(upper[0, 0] - pad, upper[-1, 0] + pad, CAVITY_GRID[0])
    y = np.linspace(upper[:, 1].min() - pad, lower[:, 1].max() + (MOUTH_OPEN_MAX + 0.1) * eye_px, CAVITY_GRID[1])
    gx, gy = np.meshgrid(x, y)
    px = np.column_stack([gx.ravel(), gy.ravel()])
    inner = list(LIPS_INNER_UPPER + LIPS_INNER_LOWER)
    z = np.full(len(px), depth[inner].mean() + CAVITY_DEPTH_MM)
    nx = CAVITY_GRID[0]
    tris = []
    for j in range(CAVITY_GRID[1] - 1):
        for i in range(nx - 1):
            a, b, c, d = j * nx + i, j * nx + i + 1, (j + 1) * nx + i, (j + 1) * nx + i + 1
            tris += [(a, c, b), (b, c, d)]
    return px, z, np.array(tris, dtype=np.int64)


def _counter_clockwise(px: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``triangles`` reordered so every one is counter-clockwise on screen (y down: negative area)."""
    p0, p1, p2 = px[triangles[:, 0]], px[triangles[:, 1]], px[triangles[:, 2]]
    area = (p1[:, 0] - p0[:, 0]) * (p2[:, 1] - p0[:, 1]) - (p1[:, 1] - p0[:, 1]) * (p2[:, 0] - p0[:, 0])
    out = triangles.copy()
    flip = area > 0
    out[flip, 1], out[flip, 2] = triangles[flip, 2], triangles[flip, 1]
    return out


def build_mesh(landmarks: np.ndarray, *, size: int) -> RealFaceMesh:
    """Fit the mesh to the photo's landmarks.

    Parameters
    ----------
    landmarks
        ``(478, 3)`` float64 from :meth:`Landmarker.detect` on the photo: x, y px, z px.
    size
        The photo's side, px.

    Returns
    -------
    RealFaceMesh
    """
    landmarks = np.asarray(landmarks, dtype=np.float64)
    if landmarks.shape != (N_LANDMARKS, 3) or not np.all(np.isfinite(landmarks)):
        raise ValueError(f"landmarks: expected finite ({N_LANDMARKS}, 3), got {landmarks.shape}")
    A = camera_matrix(size)
    lm_px = landmarks[:, :2]
    eye_px = float(np.linalg.norm(lm_px[OUTER_EYE_CORNERS[0]] - lm_px[OUTER_EYE_CORNERS[1]]))
    mm_per_px = EYE_CORNERS_MM / eye_px
    depth = A[0, 0] * mm_per_px + landmarks[:, 2] * mm_per_px
    centre_depth = depth[NOSE_TIP] + HEAD_CENTRE_BEHIND_NOSE_MM
    ring_px, ring_depth = _ring(lm_px, depth, centre_depth, size)
    skin_px = np.concatenate([lm_px, ring_px])
    skin_depth = np.concatenate([depth, ring_depth])
    tris = Delaunay(skin_px).simplices.astype(np.int64)
    mouth = PolygonPath(lm_px[list(inner_lip_polygon())])
    tris = tris[~mouth.contains_points(skin_px[tris].mean(axis=1))]
    cav_px, cav_depth, cav_tris = _cavity(lm_px, depth, eye_px)
    source_px = np.concatenate([skin_px, cav_px])
    cam = _back_project(source_px, np.concatenate([skin_depth, cav_depth]), A)
    oval_mid = lm_px[list(FACE_OVAL)].mean(axis=0)
    centre = _back_project(oval_mid[None], np.array([centre_depth]), A)[0]
    return RealFaceMesh(
        vertices=cam - centre,
        source_px=source_px,
        skin=_counter_clockwise(source_px, tris),
        cavity=_counter_clockwise(source_px, cav_tris + len(skin_px)),
        head_centre=centre,
        intrinsics=A,
        mm_per_px=mm_per_px,
        eye_px=eye_px,
        size=int(size),
    )


def mouth_texture(photo: np.ndarray, landmarks: np.ndarray, *, eye_px: float) -> np.ndarray:
    """The cavity's texture: the photo inside the inner lips (the teeth the portrait shows), a
    dark red mouth interior outside, darkening away from them.

    Parameters
    ----------
    photo
        ``(S, S, 3)`` uint8 RGB.
    landmarks
        ``(478, 3)`` px of the photo.
    eye_px
        Outer-eye-corner distance, px (sets the darkening's scale).

    Returns
    -------
    numpy.ndarray
        ``(S, S, 3)`` uint8 RGB.
    """
    h, w = photo.shape[:2]
    shift = 4
    poly = np.round(landmarks[list(inner_lip_polygon()), :2] * (1 << shift)).astype(np.int32)
    mask = np.zeros((h, w), np.uint8)
    cv2.fillPoly(mask, [poly], 255, cv2.LINE_AA, shift)
    dist = cv2.distanceTransform(255 - (mask > 127).astype(np.uint8) * 255, cv2.DIST_L2, 5)
    near, far = np.array([92.0, 30.0, 32.0]), np.array([26.0, 8.0, 10.0])
    interior = far + (near - far) * np.exp(-dist / (0.08 * eye_px))[..., None]
    alpha = cv2.GaussianBlur(mask.astype(np.float32) / 255.0, (0, 0), max(w / 512.0, 0.5))[..., None]
    return np.clip(np.round(alpha * photo + (1 - alpha) * interior), 0, 255).astype(np.uint8)
