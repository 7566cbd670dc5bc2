"""Render a face: pinhole camera (eq. 10 of Zhang et al. 2006), piecewise-affine texture mapping.

Pose convention (OpenCV, model -> camera): ``X_cam = R @ X_head + t``, pixel ``~ A @ X_cam``.
``R = Rz(roll) @ Ry(yaw) @ Rx(pitch)`` with angles in degrees; camera axes x right, y down,
z forward. Pixel coordinates have their origin at the centre of the top-left pixel.

The skin mesh is rasterized back to front into a triangle-index buffer (back faces culled), the
texture is fetched through the per-pixel barycentric coordinates (one ``cv2.remap``) and shaded
by interpolated Lambert vertex intensities. Eyeballs, the mouth interior and the teeth are drawn
first, behind the skin, and show through the openings of the mesh.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from stages.layout import Layout

from .face import Identity, make_identity, neutral_points3d
from .mesh import FaceMesh, build_mesh, vertex_positions
from .texture import Texture, build_texture, detail_strengths, frame_texture

LIGHT = np.array([-0.5, -0.55, -0.8]) / np.linalg.norm([-0.5, -0.55, -0.8])  # towards the light, camera frame
SHIFT = 4
NECK_PIVOT = np.array([0.0, 70.0, 80.0])  # clip heads turn about this head-frame point (mm), like a neck


def rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """``R = Rz(roll) @ Ry(yaw) @ Rx(pitch)`` ``(3, 3)`` from angles in degrees; independent of
    ``stages.geometry.rotation.rotation_zyx`` on purpose: the ground truth the tests compare against."""
    y, p, r = np.deg2rad([yaw, pitch, roll])
    rx = np.array([[1, 0, 0], [0, np.cos(p), -np.sin(p)], [0, np.sin(p), np.cos(p)]])
    ry = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
    rz = np.array([[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1]])
    return rz @ ry @ rx


@dataclass(frozen=True)
class Camera:
    """Pinhole camera: ``A`` ``(3, 3)`` intrinsics (px) and image ``size`` ``(W, H)``."""

    A: np.ndarray
    size: tuple[int, int]


def make_camera(size: tuple[int, int], *, focal_factor: float = 1.2) -> Camera:
    """A camera with ``fx = fy = focal_factor * max(W, H)`` and the principal point at the centre."""
    w, h = size
    f = focal_factor * max(w, h)
    return Camera(np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]]), (int(w), int(h)))


def framing_translation(camera: Camera, *, head_mm: float) -> np.ndarray:
    """Translation ``t`` (mm) that puts the head frame's point (0, 5, 0) at the image centre with
    ``head_mm`` of face height spanning the image height."""
    z = camera.A[1, 1] * head_mm / camera.size[1]
    return np.array([0.0, -5.0, z])


def project(points3d: np.ndarray, R: np.ndarray, t: np.ndarray, A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project head-frame points ``(..., 3)`` mm: returns pixels ``(..., 2)`` and camera depth ``(...)`` mm (eq. 10);
    independent of ``stages.geometry.camera`` on purpose: the ground truth the tests compare against."""
    cam = points3d @ R.T + t
    img = cam @ A.T
    return img[..., :2] / img[..., 2:3], cam[..., 2]


@dataclass
class FaceModel:
    """One identity ready to render: layout, neutral 3D points, mesh, textures per resolution."""

    identity: Identity
    layout: Layout
    neutral: np.ndarray
    mesh: FaceMesh
    textures: dict[float, Texture] = field(default_factory=dict)

    def texture(self, ppm: float) -> Texture:
        key = float(np.clip(np.round(ppm * 2) / 2, 1.0, 6.0))
        if key not in self.textures:
            self.textures[key] = build_texture(self.identity, self.layout, self.mesh, ppm=key)
        return self.textures[key]


def make_face(seed: int, layout: Layout) -> FaceModel:
    """The face of identity ``seed``."""
    identity = make_identity(seed, layout)
    return FaceModel(identity, layout, neutral_points3d(identity, layout), build_mesh(identity, layout))


@dataclass(frozen=True)
class Rendered:
    """``image (H, W, 3) uint8`` RGB; ``points (N, 2)`` px; ``visible (N,)`` bool; ``depth (N,)`` mm."""

    image: np.ndarray
    points: np.ndarray
    visible: np.ndarray
    depth: np.ndarray


def _background(size: tuple[int, int]) -> np.ndarray:
    w, h = size
    ramp = np.linspace(0.0, 1.0, h, dtype=np.float32)[:, None, None]
    top, bottom = np.array([0.62, 0.66, 0.70], np.float32), np.array([0.40, 0.43, 0.47], np.float32)
    return np.broadcast_to(top * (1 - ramp) + bottom * ramp, (h, w, 3)).copy()


def background(size: tuple[int, int]) -> np.ndarray:
    """The backdrop every render draws first: ``(H, W, 3)`` float32 sRGB in [0, 1], a vertical
    grey-blue gradient, for ``size`` = (W, H) (for compositing other renders the same way)."""
    return _background(size)


def _fx(p: np.ndarray) -> np.ndarray:
    return np.round(np.asarray(p) * (1 << SHIFT)).astype(np.int32).reshape(-1, 1, 2)


def _draw_eyes(img: np.ndarray, face: FaceModel, R: np.ndarray, t: np.ndarray, A: np.ndarray) -> None:
    """Eyeballs (sclera, iris, pupil, highlight), fixed in the head, drawn behind the lids."""
    L = face.layout
    for s in "lr":
        corners = face.neutral[[L.index(f"eye_{s}_0"), L.index(f"eye_{s}_6")]]
        radius = 12.5
        centre = corners.mean(axis=0) + np.array([0.0, 0.3, radius - 1.5])
        c_px, c_z = project(centre, R, t, A)
        r_px = A[0, 0] * radius / c_z
        cv2.circle(img, tuple(_fx(c_px)[0, 0]), int(r_px * (1 << SHIFT)), (0.86, 0.83, 0.80), -1, cv2.LINE_AA, SHIFT)
        front = centre + np.array([0.0, 0.0, -radius * 0.93])
        theta = np.linspace(0, 2 * np.pi, 28, endpoint=False)
        iris = np.asarray(face.identity.iris, dtype=np.float64)
        for rr, colour in ((5.9, iris * 0.55), (5.3, iris), (2.4, np.array([0.03, 0.03, 0.03]))):
            ring = front + np.column_stack([rr * np.cos(theta), rr * np.sin(theta), np.zeros_like(theta) + (5.9 - rr) * 0.15])
            ring_px, _ = project(ring, R, t, A)
            cv2.fillPoly(img, [_fx(ring_px)], tuple(float(v) for v in colour), cv2.LINE_AA, SHIFT)
            if rr == 5.3:
                spokes = front + np.column_stack([4.8 * np.cos(theta), 4.8 * np.sin(theta), np.zeros_like(theta)])
                sp_px, _ = project(spokes, R, t, A)
                f_px, _ = project(front, R, t, A)
                for k in range(0, len(theta), 2):
                    cv2.line(
                        img,
                        tuple(_fx(f_px)[0, 0]),
                        tuple(_fx(sp_px[k])[0, 0]),
                        tuple(float(v) for v in colour * 0.75),
                        1,
                        cv2.LINE_AA,
                        SHIFT,
                    )
        hl_px, hl_z = project(front + np.array([-1.6, -1.6, -0.5]), R, t, A)
        cv2.circle(
            img,
            tuple(_fx(hl_px)[0, 0]),
            max(int(A[0, 0] * 0.8 / hl_z * (1 << SHIFT)), 1 << SHIFT),
            (0.97, 0.97, 0.97),
            -1,
            cv2.LINE_AA,
            SHIFT,
        )


def _draw_mouth(img: np.ndarray, face: FaceModel, points3d: np.ndarray, R: np.ndarray, t: np.ndarray, A: np.ndarray) -> None:
    """Mouth interior and teeth (upper teeth on the head, lower on the jaw), behind the lips."""
    L = face.layout
    inner = points3d[[L.index(f"mouth_inner_{k}") for k in range(10)]]
    inner_px, _ = project(inner, R, t, A)
    cv2.fillPoly(img, [_fx(inner_px)], (0.20, 0.06, 0.06), cv2.LINE_AA, SHIFT)
    cv2.polylines(img, [_fx(inner_px)], True, (0.20, 0.06, 0.06), 3, cv2.LINE_AA, SHIFT)
    low_mid = inner[[6, 7, 8, 9]].mean(axis=0) + np.array([0.0, -2.0, 8.0])
    tongue = low_mid + np.column_stack(
        [11 * np.cos(np.linspace(np.pi, 2 * np.pi, 16)), 5 * np.sin(np.linspace(np.pi, 2 * np.pi, 16)), np.zeros(16)]
    )
    t_px, _ = project(tongue, R, t, A)
    cv2.fillPoly(img, [_fx(t_px)], (0.55, 0.22, 0.22), cv2.LINE_AA, SHIFT)
    for prefix, gum_dir in (("teeth_upper", -1.0), ("teeth_lower", 1.0)):
        edge = points3d[[L.index(f"{prefix}_{k}") for k in range(4)]]
        s = np.linspace(0, 3, 9)
        samples = np.column_stack([np.interp(s, np.arange(4), edge[:, k]) for k in range(3)])
        gum = samples + np.array([0.0, gum_dir * 9.0, 1.0])
        e_px, _ = project(samples, R, t, A)
        g_px, _ = project(gum, R, t, A)
        for k in range(len(s) - 1):
            bright = 0.93 - 0.35 * abs((k + 0.5) / (len(s) - 1) - 0.5) * 2 - (0.08 if gum_dir > 0 else 0.0)
            quad = np.array([e_px[k], e_px[k + 1], g_px[k + 1], g_px[k]])
            cv2.fillConvexPoly(img, _fx(quad), (bright, bright * 0.97, bright * 0.88), cv2.LINE_AA, SHIFT)
            cv2.line(img, tuple(_fx(e_px[k])[0, 0]), tuple(_fx(g_px[k])[0, 0]), (0.45, 0.40, 0.35), 1, cv2.LINE_AA, SHIFT)


def texture_ppm(camera: Camera, depth_mm: float) -> float:
    """Texture resolution (px per mm) for a face at ``depth_mm``: 1.6 texels per image pixel."""
    return 1.6 * float(camera.A[0, 0]) / depth_mm


def render(
    face: FaceModel,
    points3d: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    camera: Camera,
    *,
    supersample: int = 2,
    ppm: float | None = None,
) -> Rendered:
    """Render identity ``face`` with expression points ``points3d`` ``(N, 3)`` mm at pose (R, t).

    ``ppm`` fixes the texture resolution (a clip passes one value so the texture never switches
    resolution between frames); by default :func:`texture_ppm` at the face's median depth. Returns the image, the exact projections of ``points3d`` (eq. 10), their visibility (not
    hidden by the skin; teeth only through the open mouth) and camera depths.
    """
    A = camera.A
    w, h = camera.size
    ss = int(supersample)
    S = np.array([[ss, 0, (ss - 1) / 2.0], [0, ss, (ss - 1) / 2.0], [0, 0, 1.0]])
    A_ss = S @ A
    W, H = w * ss, h * ss
    points_px, points_z = project(points3d, R, t, A)
    verts = vertex_positions(face.mesh, points3d)
    v_px, v_z = project(verts, R, t, A_ss)
    cam = verts @ R.T + t
    tri = face.mesh.triangles
    q0, q1, q2 = v_px[tri[:, 0]], v_px[tri[:, 1]], v_px[tri[:, 2]]
    e1, e2 = q1 - q0, q2 - q0
    area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    front = area > 1e-6
    order = np.flatnonzero(front)[np.argsort(-v_z[tri[front]].mean(axis=1), kind="stable")]
    ids = np.full((H, W), -1, np.int32)
    fixed = np.round(v_px * (1 << SHIFT)).astype(np.int32)
    for k in order:
        cv2.fillConvexPoly(ids, fixed[tri[k]], int(k), cv2.LINE_8, SHIFT)
    # vertex shading (Lambert, camera frame)
    n_face = np.cross(cam[tri[:, 1]] - cam[tri[:, 0]], cam[tri[:, 2]] - cam[tri[:, 0]])
    normals = np.zeros_like(cam)
    for j in range(3):
        np.add.at(normals, tri[:, j], n_face)
    normals /= -(np.linalg.norm(normals, axis=1, keepdims=True) + 1e-12)  # counter-clockwise on screen -> towards the camera
    shade = 0.34 + 0.8 * np.clip(normals @ LIGHT, 0.0, None)
    # per-pixel barycentrics
    ys, xs = np.nonzero(ids >= 0)
    k = ids[ys, xs]
    det = area[k]
    dx, dy = xs - q0[k, 0], ys - q0[k, 1]
    b1 = (dx * e2[k, 1] - dy * e2[k, 0]) / det
    b2 = (e1[k, 0] * dy - e1[k, 1] * dx) / det
    b0 = 1.0 - b1 - b2
    tex = face.texture(ppm if ppm is not None else texture_ppm(camera, float(np.median(v_z))))
    uv_px = tex.to_px(face.mesh.uv)
    i0, i1, i2 = tri[k, 0], tri[k, 1], tri[k, 2]
    map_x = np.full((H, W), -10.0, np.float32)
    map_y = np.full((H, W), -10.0, np.float32)
    map_x[ys, xs] = b0 * uv_px[i0, 0] + b1 * uv_px[i1, 0] + b2 * uv_px[i2, 0]
    map_y[ys, xs] = b0 * uv_px[i0, 1] + b1 * uv_px[i1, 1] + b2 * uv_px[i2, 1]
    light = np.zeros((H, W), np.float32)
    light[ys, xs] = b0 * shade[i0] + b1 * shade[i1] + b2 * shade[i2]
    zbuf = np.full((H, W), np.inf)
    zbuf[ys, xs] = b0 * v_z[i0] + b1 * v_z[i1] + b2 * v_z[i2]
    colour = frame_texture(tex, detail_strengths(face.neutral, points3d, face.layout))
    skin = cv2.remap(colour, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    under = _background((W, H))
    _draw_mouth(under, face, points3d, R, t, A_ss)
    _draw_eyes(under, face, R, t, A_ss)
    covered = ids >= 0
    out = np.where(covered[..., None], skin * light[..., None], under)
    if ss > 1:
        out = cv2.resize(out, (w, h), interpolation=cv2.INTER_AREA)
    image = np.clip(np.round(out * 255.0), 0, 255).astype(np.uint8)
    visible = _visibility(face, points_px, points_z, ids, zbuf, ss)
    return Rendered(image=image, points=points_px, visible=visible, depth=points_z)


def _visibility(face: FaceModel, px: np.ndarray, z: np.ndarray, ids: np.ndarray, zbuf: np.ndarray, ss: int) -> np.ndarray:
    """True where a feature point is seen: skin points not behind other skin (depth within 2 mm
    of the farthest skin depth in the 3x3 neighbourhood of its pixel, so silhouette points count
    as seen); teeth points inside the open mouth and not covered by the lips."""
    H, W = ids.shape
    L = face.layout
    p_ss = np.round((px + 0.5) * ss - 0.5).astype(int)
    inside = (p_ss[:, 0] >= 0) & (p_ss[:, 0] < W) & (p_ss[:, 1] >= 0) & (p_ss[:, 1] < H)
    pc = np.clip(p_ss, 0, [W - 1, H - 1])
    hit = ids[pc[:, 1], pc[:, 0]] >= 0
    far = cv2.dilate(np.where(ids >= 0, zbuf, 1e9).astype(np.float32), np.ones((3, 3), np.uint8))
    seen = z <= far[pc[:, 1], pc[:, 0]] + 2.0
    inner = px[[L.index(f"mouth_inner_{k}") for k in range(10)]].astype(np.float32).reshape(-1, 1, 2)
    vis = np.zeros(L.n_points, dtype=bool)
    for i, name in enumerate(L.point_names):
        if not inside[i]:
            continue
        if name.startswith("teeth_"):
            in_mouth = cv2.pointPolygonTest(inner, (float(px[i, 0]), float(px[i, 1])), True) > 0.5
            vis[i] = bool(in_mouth and not hit[i])
        else:
            vis[i] = bool(seen[i])
    return vis
