"""Render the textured mesh: pinhole projection, z-buffer, perspective-correct bilinear texturing.

A frame is rendered at ``supersample`` times its size (intrinsics ``S A`` with
``S = [[s, 0, (s-1)/2], [0, s, (s-1)/2], [0, 0, 1]]``, which keeps the pixel-centre origin) and
reduced with ``cv2.INTER_AREA`` (the mean of each ``s x s`` block). The skin is z-buffered
(triangles may fold over each other at large yaw); the mouth cavity is drawn wherever the skin
leaves a hole (the opening between the inner lips), z-buffered among its own triangles.

With a *backdrop* (:func:`lab.realface.mesh.clean_plate`) the scene is a person in front of a
static background: the head (the face and the rings of hair, ears and neck, ``mesh.head``) turns
and moves, the backdrop stays where it is and shows wherever the head does not cover it (what a
turned head uncovers is the inpainted plate, a guess every method has to make too). Without one,
the whole mesh, out to the square beyond the frame, moves with the head.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from stages.eigen.facegen.render import project

from .landmarks import N_LANDMARKS
from .mesh import RealFaceMesh

VISIBLE_TOLERANCE_MM = 2.0
ROW = 1024  # texture lookups are laid out in rows of this many samples for cv2.remap


@dataclass(frozen=True)
class Raster:
    """The pixels of an ``(H, W)`` grid covered by a rasterization, as scanline spans.

    Attributes
    ----------
    pixel : (n,) int64
        Covered pixels, flat indices ``y * W + x``, each once, ascending.
    x : (n,) float64
        Their column.
    span : (n,) int64
        The span (one row of one triangle) that holds each pixel: that of the nearest triangle.
    corners : (s, 3) int64
        Each span's triangle's vertex indices.
    a, c : (s, 3) float64
        Screen-space barycentric coordinates along each span: ``b_k = a_k x + c_k``.
    inv_z : (V,) float64
        1 / camera depth of each vertex.
    inv_depth : (H, W) float64
        1 / camera depth of the nearest surface (0 where none).
    """

    pixel: np.ndarray
    x: np.ndarray
    span: np.ndarray
    corners: np.ndarray
    a: np.ndarray
    c: np.ndarray
    inv_z: np.ndarray
    inv_depth: np.ndarray


def _spans(p: np.ndarray, area: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, ...]:
    """Scanline spans of triangles ``p (F, 3, 2)``: for every row crossing a triangle, the
    triangle, the row ``y``, the first and last covered column, and the barycentric coefficients
    ``(a, c)`` ``(rows, 3)`` such that ``b_k = a_k x + c_k`` on that row.

    ``b_k = cross(P_k+2 - P_k+1, X - P_k+1) / area`` (the sub-triangle opposite vertex k); a
    pixel centre is covered when all three are >= 0.
    """
    h, w = shape
    y_lo = np.maximum(np.ceil(p[:, :, 1].min(axis=1)), 0).astype(np.int64)
    y_hi = np.minimum(np.floor(p[:, :, 1].max(axis=1)), h - 1).astype(np.int64)
    rows = np.maximum(y_hi - y_lo + 1, 0)
    t = np.repeat(np.arange(len(p)), rows)
    y = y_lo[t] + np.arange(int(rows.sum())) - np.repeat(np.cumsum(rows) - rows, rows)
    start = p[:, [1, 2, 0]]
    edge = p[:, [2, 0, 1]] - start  # (F, 3, 2): edge k from P_k+1 to P_k+2
    a = -edge[t, :, 1] / area[t, None]
    c = (edge[t, :, 0] * (y[:, None] - start[t, :, 1]) + edge[t, :, 1] * start[t, :, 0]) / area[t, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = -c / a
    x_lo = np.max(np.where(a > 0, bound, -np.inf), axis=1)
    x_hi = np.min(np.where(a < 0, bound, np.inf), axis=1)
    x_hi = np.where(np.any((a == 0) & (c < 0), axis=1), -np.inf, x_hi)
    first = np.maximum(np.ceil(x_lo - 1e-9), 0)
    last = np.minimum(np.floor(x_hi + 1e-9), w - 1)
    ok = last >= first
    return t[ok], y[ok], first[ok].astype(np.int64), last[ok].astype(np.int64), a[ok], c[ok]


def rasterize(px: np.ndarray, depth: np.ndarray, triangles: np.ndarray, shape: tuple[int, int]) -> Raster:
    """Z-buffered scanline rasterization of pixel centres (a pixel belongs to the nearest
    triangle that contains its centre; ``1/z`` is linear on screen, exact for planar triangles).

    Parameters
    ----------
    px
        ``(V, 2)`` projected vertices, px (origin at the centre of the top-left pixel).
    depth
        ``(V,)`` camera depths (positive), any unit.
    triangles
        ``(F, 3)`` vertex indices.
    shape
        ``(H, W)`` of the grid.

    Returns
    -------
    Raster
    """
    h, w = shape
    inv_z = 1.0 / depth
    p = px[triangles]
    area = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 1, 1] - p[:, 0, 1]) * (p[:, 2, 0] - p[:, 0, 0])
    keep = np.flatnonzero((np.abs(area) > 1e-9) & np.all(depth[triangles] > 0, axis=1))
    t, y, first, last, a, c = _spans(p[keep], area[keep], shape)
    corners = triangles[keep[t]]
    iz_a = np.einsum("sk,sk->s", a, inv_z[corners])
    iz_c = np.einsum("sk,sk->s", c, inv_z[corners])
    n = last - first + 1
    pix = np.arange(int(n.sum())) + np.repeat(y * w + first - (np.cumsum(n) - n), n)
    iz = np.repeat(iz_a, n) * pix + np.repeat(iz_c - iz_a * (y * w), n)  # = iz_a x + iz_c on row y
    span = np.repeat(np.arange(len(n)), n)
    best = np.zeros(h * w)
    np.maximum.at(best, pix, iz)
    owner = np.full(h * w, -1, np.int64)
    win = np.flatnonzero(iz >= best[pix])
    owner[pix[win]] = span[win]  # one of the equally near candidates (ties: a shared edge)
    pix = np.flatnonzero(owner >= 0)
    return Raster(
        pixel=pix,
        x=(pix % w).astype(np.float64),
        span=owner[pix],
        corners=corners,
        a=a,
        c=c,
        inv_z=inv_z,
        inv_depth=best.reshape(h, w),
    )


def interpolate(raster: Raster, values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Perspective-correct interpolation of per-vertex ``values`` ``(V, k)`` at a raster's pixels,
    each vertex weighted by ``weights`` ``(V,)``.

    A surface point with screen barycentrics ``b`` has 3D barycentrics ``b_i / z_i``
    (normalized); the result is ``sum b_i g_i v_i / sum b_i g_i`` with ``g_i = weights_i / z_i``
    (``weights = 1``: the attribute at the 3D point). Both sums are linear in ``x`` along a span,
    so they are formed per span and evaluated per pixel. Returns ``(n, k)``.
    """
    g = raster.inv_z[raster.corners] * weights[raster.corners]
    v = values[raster.corners]  # (s, 3, k)
    num_a, num_c = np.einsum("sj,sj,sjk->sk", raster.a, g, v), np.einsum("sj,sj,sjk->sk", raster.c, g, v)
    den_a, den_c = np.einsum("sj,sj->s", raster.a, g), np.einsum("sj,sj->s", raster.c, g)
    coef_a = np.column_stack([num_a, den_a])[raster.span]
    coef = np.column_stack([num_c, den_c])[raster.span]
    coef += coef_a * raster.x[:, None]
    return coef[:, :-1] / coef[:, -1:]


def sample_texture(texture: np.ndarray, uv: np.ndarray, uv_depth: np.ndarray, raster: Raster) -> np.ndarray:
    """Projective texture lookup at a raster's pixels: bilinear (``cv2.remap``, border reflected).

    The texture is the photo, a view of the neutral mesh from the camera at the identity pose,
    so a surface point's texture coordinate is its projection in that view: with 3D barycentric
    weights ``w_i`` and the vertices' depths ``z0_i`` in that view,
    ``uv = sum w_i z0_i uv_i / sum w_i z0_i`` (:func:`interpolate` with ``weights = z0``).

    Parameters
    ----------
    texture
        ``(h, w, 3)`` float32.
    uv
        ``(V, 2)`` texture px per vertex.
    uv_depth
        ``(V,)`` the vertices' depths ``z0`` in the texture's view.
    raster
        Where to sample.

    Returns
    -------
    numpy.ndarray
        ``(n, 3)`` float32, the colour of each of ``raster.pixel``.
    """
    n = len(raster.pixel)
    coords = np.full((-(-n // ROW) * ROW, 2), -1.0, np.float32)
    coords[:n] = interpolate(raster, uv, uv_depth)
    coords = coords.reshape(-1, ROW, 2)
    out = cv2.remap(texture, coords[..., 0], coords[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    return out.reshape(-1, 3)[:n]


@dataclass(frozen=True)
class Frame:
    """A rendered frame and its truth.

    ``image (S, S, 3) uint8`` RGB; ``points (478, 2)`` px, the landmarks' exact projections;
    ``visible (478,)`` bool; ``depth (478,)`` mm camera depth; ``coverage (S, S) float32``, the
    fraction of each pixel the rendered mesh covers (the head's matte with a backdrop, 1 without).
    """

    image: np.ndarray
    points: np.ndarray
    visible: np.ndarray
    depth: np.ndarray
    coverage: np.ndarray


def render(
    mesh: RealFaceMesh,
    textures: tuple[np.ndarray, np.ndarray],
    vertices: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    *,
    supersample: int = 2,
    backdrop: np.ndarray | None = None,
) -> Frame:
    """Render head-frame ``vertices`` ``(V, 3)`` mm at pose ``X_cam = R X + t``.

    Parameters
    ----------
    mesh
        The fitted mesh (triangles, texture coordinates, intrinsics).
    textures
        ``(photo, mouth)``, each ``(S, S, 3)`` float32 RGB 0..255: the skin's and the cavity's.
    vertices
        Deformed head-frame vertices (:func:`expression.deform`).
    R, t
        ``(3, 3)`` rotation, ``(3,)`` translation mm.
    supersample
        Samples per pixel along each axis.
    backdrop
        ``(S, S, 3)`` uint8 RGB, optional: a static background behind the head (module docstring).
    """
    ss = int(supersample)
    if ss < 1:
        raise ValueError(f"supersample: expected an int >= 1, got {supersample}")
    size = mesh.size
    S = np.array([[ss, 0, (ss - 1) / 2.0], [0, ss, (ss - 1) / 2.0], [0, 0, 1.0]])
    v_px, v_z = project(vertices, R, t, S @ mesh.intrinsics)
    grid = (size * ss, size * ss)
    skin = rasterize(v_px, v_z, mesh.skin if backdrop is None else mesh.head, grid)
    cavity = rasterize(v_px, v_z, mesh.cavity, grid)
    colour = np.zeros((grid[0] * grid[1], 3), np.float32)
    covered = np.zeros(grid[0] * grid[1], np.float32)
    if backdrop is not None:
        colour[:] = cv2.resize(backdrop.astype(np.float32), grid[::-1], interpolation=cv2.INTER_NEAREST).reshape(-1, 3)
    z0 = mesh.vertices[:, 2] + mesh.head_centre[2]
    colour[cavity.pixel] = sample_texture(textures[1], mesh.source_px, z0, cavity)
    colour[skin.pixel] = sample_texture(textures[0], mesh.source_px, z0, skin)
    covered[cavity.pixel] = covered[skin.pixel] = 1.0
    colour = colour.reshape(grid + (3,))
    covered = covered.reshape(grid)
    if ss > 1:
        colour = cv2.resize(colour, (size, size), interpolation=cv2.INTER_AREA)
        covered = cv2.resize(covered, (size, size), interpolation=cv2.INTER_AREA)
    image = np.clip(np.round(colour), 0, 255).astype(np.uint8)
    points, depth = project(vertices[:N_LANDMARKS], R, t, mesh.intrinsics)
    cam = vertices @ R.T + t
    visible = _front_facing(cam, mesh.skin)[:N_LANDMARKS] & _unoccluded(points, depth, skin.inv_depth, ss)
    return Frame(
        image=image,
        points=points,
        visible=visible,
        depth=depth,
        coverage=covered if backdrop is not None else np.ones((size, size), np.float32),
    )


def _front_facing(cam: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``(V,)`` True where the area-weighted vertex normal faces the camera (``n . X < 0``);
    triangles are counter-clockwise on screen, so their normals point towards the camera."""
    n_face = np.cross(cam[triangles[:, 1]] - cam[triangles[:, 0]], cam[triangles[:, 2]] - cam[triangles[:, 0]])
    normals = np.zeros_like(cam)
    for j in range(3):
        np.add.at(normals, triangles[:, j], n_face)
    return np.einsum("vd,vd->v", normals, cam) < 0


def _unoccluded(points: np.ndarray, depth: np.ndarray, inv_depth: np.ndarray, ss: int) -> np.ndarray:
    """``(N,)`` True where a point is inside the frame and not behind the skin: its depth is
    within :data:`VISIBLE_TOLERANCE_MM` of the farthest skin depth in the 3 x 3 supersampled
    neighbourhood of its pixel (so points on a silhouette count as seen)."""
    h, w = inv_depth.shape
    q = np.round((points + 0.5) * ss - 0.5).astype(np.int64)
    inside = (q[:, 0] >= 0) & (q[:, 0] < w) & (q[:, 1] >= 0) & (q[:, 1] < h)
    q = np.clip(q, 0, [w - 1, h - 1])
    far = cv2.erode(inv_depth.astype(np.float32), np.ones((3, 3), np.uint8))  # smallest 1/z = farthest
    far_depth = 1.0 / np.maximum(far[q[:, 1], q[:, 0]], 1e-12)
    return inside & (depth <= far_depth + VISIBLE_TOLERANCE_MM)
