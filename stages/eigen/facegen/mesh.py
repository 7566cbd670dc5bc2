"""The face mesh: the layout's 3D feature points plus extra vertices, triangulated in texture space.

Texture space ("canonical", mm) is the identity's neutral frontal (x, y) with the mouth drawn
open (inner lip lines apart), so the mouth opening and the eye openings have area there: the
triangles inside them are left out of the mesh and show the mouth interior and the eyeballs
rendered behind the skin. Extra vertices move with the feature points by fixed interpolation
weights (normalized Gaussians of the texture-space distance, cut across the mouth and eye slits).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import Delaunay

from stages.layout import Layout

from .face import Identity, depth, neutral_points3d

GRID_MM = 4.5
HEAD_A, HEAD_B, HEAD_Y0, HEAD_C = 86.0, 130.0, 8.0, 95.0  # head ellipsoid of face.depth (mm)
WRAP = 0.2  # texture space reaches 1 + WRAP ellipse radii; that band wraps round to the back
MOUTH_OPEN_UP, MOUTH_OPEN_DOWN = 2.5, 3.5  # inner lip lines apart in texture space (mm)


@dataclass(frozen=True)
class FaceMesh:
    """Mesh of one identity.

    ``skin`` ``(S,)`` layout indices of the feature points that are mesh vertices (all but teeth);
    ``uv`` ``(V, 2)`` texture-space vertex positions (mm), the first S are the skin feature points;
    ``canon3d`` ``(V, 3)`` their 3D positions in texture space (mm); ``weights`` ``(V - S, S)``
    interpolation weights of the extra vertices; ``triangles`` ``(F, 3)`` vertex indices,
    counter-clockwise on screen for a front-facing triangle; ``feature_uv`` ``(N, 2)`` texture-space
    positions of all layout points (teeth included).
    """

    skin: np.ndarray
    uv: np.ndarray
    canon3d: np.ndarray
    weights: np.ndarray
    triangles: np.ndarray
    feature_uv: np.ndarray


def _outline(layout: Layout, prefix: str, count: int) -> list[int]:
    return [layout.index(f"{prefix}_{k}") for k in range(count)]


def feature_uv(identity: Identity, layout: Layout) -> np.ndarray:
    """Texture-space positions ``(N, 2)`` mm of the layout points: neutral, inner lips apart."""
    uv = neutral_points3d(identity, layout)[:, :2].copy()
    inner = _outline(layout, "mouth_inner", 10)
    corners = uv[[inner[0], inner[5]]]
    half = max(abs(corners[1, 0] - corners[0, 0]) / 2.0, 1.0)
    cx = corners.mean(axis=0)[0]
    for k in range(1, 10):
        if k == 5:
            continue
        i = inner[k]
        profile = np.sqrt(max(1.0 - ((uv[i, 0] - cx) / half) ** 2, 0.0))
        uv[i, 1] += (-MOUTH_OPEN_UP if k < 5 else MOUTH_OPEN_DOWN) * profile
    return uv


def _slit_labels(uv: np.ndarray, feat: np.ndarray, layout: Layout) -> np.ndarray:
    """Which side of each slit (mouth, left eye, right eye) a texture-space point is on.

    Returns ``(P, 3)`` in {-1, 0, 1}: -1 above the slit's centre line, +1 below, 0 away from it.
    """
    out = np.zeros((len(uv), 3), dtype=np.int8)
    slits = [(_outline(layout, "mouth_inner", 10), 0, 5, 6.0, 24.0)]  # wide openings: no upper-lip pull below the lower lip
    for s in "lr":
        slits.append((_outline(layout, f"eye_{s}", 12), 0, 6, 2.0, 12.0))
    for k, (ring, a, b, margin, reach) in enumerate(slits):
        pa, pb = feat[ring[a]], feat[ring[b]]
        lo, hi = min(pa[0], pb[0]) - margin, max(pa[0], pb[0]) + margin
        t = np.clip((uv[:, 0] - pa[0]) / (pb[0] - pa[0]), 0.0, 1.0)
        line_y = pa[1] + t * (pb[1] - pa[1])
        near = (uv[:, 0] > lo) & (uv[:, 0] < hi) & (np.abs(uv[:, 1] - line_y) < reach)
        out[near, k] = np.where(uv[near, 1] > line_y[near], 1, -1)
    return out


def build_mesh(identity: Identity, layout: Layout) -> FaceMesh:
    """Build the mesh of one identity (deterministic)."""
    feat = feature_uv(identity, layout)
    names = layout.point_names
    skin = np.array([i for i, n in enumerate(names) if not n.startswith("teeth_")])
    rings = [(_outline(layout, f"eye_{s}", 12), True) for s in "lr"]
    rings += [(_outline(layout, "mouth_inner", 10), True), (_outline(layout, "mouth_outer", 16), True)]
    rings += [(_outline(layout, f"brow_{s}", 8), True) for s in "lr"]
    rings += [
        (_outline(layout, "contour", 17), False),
        ([layout.index(n) for n in ("temple_l", *[f"hairline_{k}" for k in range(5)], "temple_r")], False),
    ]
    skin_pos = {int(p): k for k, p in enumerate(skin)}
    mids, mid_rows = [], []
    for ring, closed in rings:
        pairs = list(zip(ring, ring[1:] + ring[:1])) if closed else list(zip(ring, ring[1:]))
        for a, b in pairs:
            if np.linalg.norm(feat[a] - feat[b]) > 3.0:
                mids.append((feat[a] + feat[b]) / 2.0)
                row = np.zeros(len(skin))
                row[skin_pos[a]] = row[skin_pos[b]] = 0.5
                mid_rows.append(row)
    mids_arr = np.array(mids)
    holes = [feat[_outline(layout, f"eye_{s}", 12)] for s in "lr"] + [feat[_outline(layout, "mouth_inner", 10)]]
    xs = np.arange(-HEAD_A, HEAD_A + 1e-9, GRID_MM)
    ys = np.arange(HEAD_Y0 - HEAD_B, HEAD_Y0 + HEAD_B + 1e-9, GRID_MM * np.sqrt(3) / 2)
    grid = []
    for r, y in enumerate(ys):
        for x in xs + (GRID_MM / 2 if r % 2 else 0.0):
            if (x / HEAD_A) ** 2 + ((y - HEAD_Y0) / HEAD_B) ** 2 <= (1.0 + WRAP) ** 2:
                grid.append((x, y))
    grid_arr = np.array(grid)
    known = np.vstack([feat[skin], mids_arr])
    dist = np.min(np.linalg.norm(grid_arr[:, None, :] - known[None, :, :], axis=2), axis=1)
    keep = dist > 0.65 * GRID_MM
    for poly in holes:
        contour = poly.astype(np.float32).reshape(-1, 1, 2)
        inside = np.array([cv2.pointPolygonTest(contour, (float(x), float(y)), True) for x, y in grid_arr])
        keep &= inside < -1.0
    grid_arr = grid_arr[keep]
    extras = np.vstack([mids_arr, grid_arr])
    uv = np.vstack([feat[skin], extras])
    # interpolation weights of the grid vertices: adaptive normalized Gaussians, cut across slits
    d = np.linalg.norm(grid_arr[:, None, :] - feat[skin][None, :, :], axis=2)
    sigma = np.clip(np.sort(d, axis=1)[:, 2], 4.0, 14.0)[:, None]
    logw = -0.5 * (d / sigma) ** 2
    logw -= logw.max(axis=1, keepdims=True)
    w = np.exp(logw)
    lab_g = _slit_labels(grid_arr, feat, layout)
    lab_f = _slit_labels(feat[skin], feat, layout)
    crossing = np.any(lab_g[:, None, :] * lab_f[None, :, :] < 0, axis=2)
    w = np.where(crossing, w * 1e-4, w)
    w /= w.sum(axis=1, keepdims=True)
    weights = np.vstack([np.array(mid_rows), w])
    tri = Delaunay(uv).simplices.astype(np.int64)
    centroids = uv[tri].mean(axis=1)
    keep_t = np.ones(len(tri), dtype=bool)
    for poly in holes:
        contour = poly.astype(np.float32).reshape(-1, 1, 2)
        keep_t &= np.array([cv2.pointPolygonTest(contour, (float(x), float(y)), False) < 0 for x, y in centroids])
    tri = tri[keep_t]
    p0, p1, p2 = uv[tri[:, 0]], uv[tri[:, 1]], uv[tri[:, 2]]
    area = (p1[:, 0] - p0[:, 0]) * (p2[:, 1] - p0[:, 1]) - (p1[:, 1] - p0[:, 1]) * (p2[:, 0] - p0[:, 0])
    tri = np.where((area < 0)[:, None], tri[:, [0, 2, 1]], tri)
    canon3d = surface(uv, identity.depth_params)
    return FaceMesh(skin=skin, uv=uv, canon3d=canon3d, weights=weights, triangles=tri, feature_uv=feat)


def surface(uv: np.ndarray, params: dict[str, float]) -> np.ndarray:
    """3D head-frame position ``(P, 3)`` mm of texture-space points ``(P, 2)`` mm.

    Inside the head ellipse: ``(u, v, depth(u, v))``. Outside it (the band up to ``1 + WRAP``
    radii) the surface wraps round the ellipsoid towards the back, so the silhouette stays
    closed at large head rotations.
    """
    u, v = uv[:, 0], uv[:, 1]
    rho = np.sqrt((u / HEAD_A) ** 2 + ((v - HEAD_Y0) / HEAD_B) ** 2)
    out = np.column_stack([u, v, depth(u, v, params)])
    band = rho > 1.0
    if band.any():
        r = rho[band]
        ue, ve = u[band] / r, HEAD_Y0 + (v[band] - HEAD_Y0) / r
        phi = (r - 1.0) / WRAP * (np.pi / 2)
        out[band, 0] = ue * np.cos(phi)
        out[band, 1] = HEAD_Y0 + (ve - HEAD_Y0) * np.cos(phi)
        out[band, 2] = depth(ue, ve, params) + HEAD_C * np.sin(phi)
    return out


def vertex_positions(mesh: FaceMesh, points3d: np.ndarray) -> np.ndarray:
    """3D positions ``(V, 3)`` mm of all mesh vertices for feature points ``points3d`` ``(N, 3)``.

    Extra vertex = its texture-space 3D position + the weighted feature-point displacements.
    """
    skin_now = points3d[mesh.skin]
    s = len(mesh.skin)
    disp = skin_now - mesh.canon3d[:s]
    return np.vstack([skin_now, mesh.canon3d[s:] + mesh.weights @ disp])
