"""The head surround: the face's feature points extended to hair, ears, neck and the background.

The synthesis warp (Sec. 7, last paragraph) moves the whole image by a triangulation over the
feature points and *anchor points*. The anchors here describe what lies around the face, in the
standard geometry, in three kinds:

``RING_HEAD`` (kind 1)
    The convex hull of the feature points scaled about its centroid, each hull point by its own
    scale ``s``: where the head ends along that ray (:func:`head_extent`: the hair and ears of a
    person segmented from the image, at least ``RING_SCALES[0]``), or ``RING_SCALES[0]`` below
    the mouth, where the neck goes on into the shoulders. It turns with the head (motion weight
    1) and lies behind the face outline, each point ``(s - 1) r`` behind the hull point it was
    scaled from (``r`` the face's radius in mm: the RMS distance of the lifted hull points from
    their centroid across the image plane), so the depth falls off from the face to the sides of
    the head.
``RING_OUTER`` (kind 2)
    The head ring's scale plus ``RING_SCALES[1] - RING_SCALES[0]``: the background beside the
    head. Static (weight 0), ``(s - 1) r`` behind its hull point as well.
``BORDER`` (kind 0)
    Points on the image's outer pixel edges, and a rectangle further out
    (:func:`stages.synthesis.warp.border_anchors` with a margin, so that a warp moving every
    anchor still covers the whole output): the background, static.

Ring points outside the image are left out, and the triangulation (:func:`surround_triangles`) is
made of two parts that meet at the image's edge: one over the feature points, the rings and the
points on the image's edge (the mouth's outline made edges of it), one over those edge points and
the outer rectangle. So the image's
edge is made of triangle edges: a warp that keeps the anchors where they are (the alignment of
the examples to the standard geometry, Sec. 5.2) maps the image's edge onto itself and never
reaches beyond it.

Between the head ring and the outer ring (or the image's edge) the motion weight goes from 1 to 0:
when the head turns or moves, that band of background is compressed on one side and stretched on
the other, the background beyond it stays where it is, and the head inside the ring, hair and
ears included, moves as one body. The *head matte* is the region inside the head ring (its
points outside the image included), its edge softened.
"""

from __future__ import annotations

import numpy as np

from stages.synthesis.warp import border_anchors

__all__ = [
    "RING_SCALES",
    "BORDER",
    "RING_HEAD",
    "RING_OUTER",
    "head_ring",
    "head_extent",
    "surround_anchors",
    "surround_triangles",
    "head_matte",
    "anchor_depth",
    "motion_weights",
]

RING_SCALES = (1.3, 1.7)
RING_MAX_SCALE = 2.2  # the largest head ring, times the face's hull
RING_MARGIN = 0.06  # the head ring beyond where the segmented head ends, in hull scale
SEGMENT_SIDE = 192  # px: the longer side of the image the head is segmented in
BORDER, RING_HEAD, RING_OUTER = 0, 1, 2
HEAD_MATTE_SOFTNESS = 0.04  # Gaussian sigma of the head matte's edge, fraction of the face's radius (px)
EDGE_SPACING = 0.125  # points on the image's edge: this fraction of the longer side apart, at most


def _hull(points: np.ndarray) -> np.ndarray:
    """Indices of the convex hull of ``points (N, 2)``, counter-clockwise (y up) order."""
    from scipy.spatial import ConvexHull

    return ConvexHull(points).vertices.astype(np.int64)


def head_ring(points: np.ndarray, face: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The hull of the face points ``points[face]`` and its centroid: ``(hull indices (h,), centre (2,))``."""
    idx = np.flatnonzero(np.asarray(face, bool))
    ring_idx = idx[_hull(np.asarray(points, np.float64)[idx])]
    return ring_idx, np.asarray(points, np.float64)[ring_idx].mean(0)


def head_extent(image: np.ndarray, points: np.ndarray, face: np.ndarray, *, iterations: int = 3) -> np.ndarray:
    """Per hull point of the face, the scale about the hull's centroid at which the head ends.

    The person is segmented from the image by GrabCut (Rother et al. 2004, OpenCV), seeded with
    the face's hull as certain foreground, ``RING_MAX_SCALE`` times the hull as probable foreground,
    the rest as probable background and a band along the top and the sides of the image as
    certain background; the region connected to the face is the head. Along each ray from the
    centroid through a hull point the head ends where the segment first leaves it; the head ring
    lies ``RING_MARGIN`` beyond that, between ``RING_SCALES[0]`` and ``RING_MAX_SCALE``. Hull
    points below the mouth (farther down than the hull's centroid by half the face's radius,
    across the eye line) keep ``RING_SCALES[0]``: below them the neck goes on into the shoulders,
    and the band there is what bends.

    Parameters
    ----------
    image : (H, W, 3) uint8
        RGB, the geometry of ``points`` (the pack's neutral).
    points : (N, 2) float, px
    face : (N,) bool
        The points whose hull is the face outline.

    Returns
    -------
    (N,) float64: the head ring's scale at each hull point (``RING_SCALES[0]`` at the others).
    """
    import cv2

    points = np.asarray(points, np.float64)
    H, W = image.shape[:2]
    ring_idx, centre = head_ring(points, face)
    hull = points[ring_idx]
    f = min(1.0, SEGMENT_SIDE / max(W, H))  # segmented at most SEGMENT_SIDE px across
    w, h = max(round(W * f), 1), max(round(H * f), 1)

    def polygon(scale: float) -> np.ndarray:
        return np.round(f * (centre + scale * (hull - centre))).astype(np.int32)

    mask = np.full((h, w), cv2.GC_PR_BGD, np.uint8)
    cv2.fillPoly(mask, [polygon(RING_MAX_SCALE)], cv2.GC_PR_FGD)
    band = max(2, round(0.02 * max(w, h)))
    mask[:band], mask[:, :band], mask[:, -band:] = cv2.GC_BGD, cv2.GC_BGD, cv2.GC_BGD
    cv2.fillPoly(mask, [polygon(1.0)], cv2.GC_FGD)
    bgd, fgd = np.zeros((1, 65)), np.zeros((1, 65))
    small = cv2.resize(np.ascontiguousarray(image[..., ::-1]), (w, h), interpolation=cv2.INTER_AREA)
    cv2.grabCut(small, mask, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    person = ((mask == cv2.GC_FGD) | (mask == cv2.GC_PR_FGD)).astype(np.uint8)
    _, labels = cv2.connectedComponents(person)
    inside = polygon(1.0).mean(0).astype(int)
    head = labels == labels[np.clip(inside[1], 0, h - 1), np.clip(inside[0], 0, w - 1)]
    steps = np.arange(1.0, RING_MAX_SCALE + 1e-9, 0.02)
    rays = centre + steps[None, :, None] * (hull - centre)[:, None, :]  # (h, S, 2)
    x = np.clip(np.round(f * rays[..., 0]).astype(int), 0, w - 1)
    y = np.clip(np.round(f * rays[..., 1]).astype(int), 0, h - 1)
    within = (rays[..., 0] >= 0) & (rays[..., 0] <= W - 1) & (rays[..., 1] >= 0) & (rays[..., 1] <= H - 1)
    on = head[y, x] & within
    first_off = np.where(~on.all(axis=1), np.argmin(on, axis=1), len(steps))  # per ray, the first step off the head
    last_on = np.concatenate([[1.0], steps])[first_off]  # the step before it (the hull itself when none is on)
    scale = np.clip(last_on + RING_MARGIN, RING_SCALES[0], RING_MAX_SCALE)
    radius = np.sqrt(((hull - centre) ** 2).sum(1).mean())
    left, right = hull[np.argmin(hull[:, 0])], hull[np.argmax(hull[:, 0])]
    down = np.array([-(right - left)[1], (right - left)[0]]) / max(np.linalg.norm(right - left), 1e-9)
    scale[(hull - centre) @ down > 0.5 * radius] = RING_SCALES[0]
    out = np.full(len(points), RING_SCALES[0])
    out[ring_idx] = scale
    return out


def surround_anchors(
    points: np.ndarray,
    size: tuple[int, int],
    *,
    face: np.ndarray,
    per_side: int = 4,
    margin: float = 0.25,
    head_scale: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The anchors of the synthesis model: the two rings and the border (module docstring).

    Parameters
    ----------
    points : (N, 2) float, px
        The feature points of the standard geometry.
    size : (W, H)
    face : (N,) bool
        The points whose hull is the face outline (the layout's points but the teeth).
    per_side, margin
        The outer rectangle (:func:`stages.synthesis.warp.border_anchors`).
    head_scale : (N,) float, optional
        The head ring's scale at each hull point (:func:`head_extent`, computed on the same face
        in any geometry); ``RING_SCALES[0]`` at every point when omitted.

    Returns
    -------
    anchors : (A, 2) float64, px: the head ring, the outer ring (the points inside the image),
        the points on the image's edge, the outer rectangle
    kind : (A,) int8: ``RING_HEAD``, ``RING_OUTER`` or ``BORDER``
    hull : (A,) int64: the feature point a ring anchor is scaled from (-1 for the border)
    """
    points = np.asarray(points, np.float64)
    W, H = size
    ring_idx, centre = head_ring(points, face)
    head = np.full(len(ring_idx), RING_SCALES[0]) if head_scale is None else np.asarray(head_scale, np.float64)[ring_idx]
    anchors, kinds, hulls = [], [], []
    for kind, scale in ((RING_HEAD, head), (RING_OUTER, head + RING_SCALES[1] - RING_SCALES[0])):
        ring = centre + scale[:, None] * (points[ring_idx] - centre)
        inside = np.all((ring > 1.0) & (ring < np.array([W, H]) - 2.0), axis=1)
        anchors.append(ring[inside])
        kinds.append(np.full(int(inside.sum()), kind, np.int8))
        hulls.append(ring_idx[inside])
    edge = border_anchors(size, per_side=max(per_side, int(np.ceil(1.0 / EDGE_SPACING))), margin=0.0)
    outer = border_anchors(size, per_side=per_side, margin=margin)
    anchors += [edge, outer]
    kinds.append(np.full(len(edge) + len(outer), BORDER, np.int8))
    hulls.append(np.full(len(edge) + len(outer), -1, np.int64))
    return np.concatenate(anchors), np.concatenate(kinds), np.concatenate(hulls)


def _inside_polygon(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """``(n,) bool``: which of ``points (n, 2)`` lie inside the closed ``polygon (m, 2)``."""
    from matplotlib.path import Path as PolygonPath

    return PolygonPath(polygon).contains_points(points)


def _cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))


def _crosses(p: np.ndarray, q: np.ndarray, a: np.ndarray, b: np.ndarray) -> bool:
    """Whether the open segments ``pq`` and ``ab`` cross (not merely touch)."""
    d1, d2 = _cross(a, b, p), _cross(a, b, q)
    d3, d4 = _cross(p, q, a), _cross(p, q, b)
    return d1 * d2 < 0 and d3 * d4 < 0


def constrain(triangles: np.ndarray, vertices: np.ndarray, edges: list[tuple[int, int]]) -> np.ndarray:
    """Make each of ``edges`` an edge of the triangulation by edge flips (Lawson's method of
    inserting a constraint into a triangulation; the result still tiles the same region).

    Parameters
    ----------
    triangles : (K, 3) int, a triangulation of ``vertices (P, 2)`` (Delaunay)
    edges : vertex index pairs that must be triangle edges (the mouth's outline)

    Returns
    -------
    (K, 3) int32. An edge that no flip sequence inserts (an outline that crosses itself or runs
    through another point, as random or degenerate geometry can) is left out; the rest stand.
    """
    tri = [list(t) for t in np.asarray(triangles)]
    v = np.asarray(vertices, np.float64)
    for a, b in edges:
        for _ in range(4 * len(tri)):
            if any(a in t and b in t for t in tri):
                break
            flipped = False
            for k, t in enumerate(tri):
                for u, w in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0])):
                    if a in (u, w) or b in (u, w) or not _crosses(v[u], v[w], v[a], v[b]):
                        continue
                    other = next((m for m, s in enumerate(tri) if m != k and u in s and w in s), None)
                    if other is None:
                        continue
                    p = next(x for x in t if x not in (u, w))
                    q = next(x for x in tri[other] if x not in (u, w))
                    if not _crosses(v[p], v[q], v[u], v[w]):
                        continue  # not a convex quad: flip another crossing edge first
                    tri[k], tri[other] = [p, q, w], [q, p, u]
                    flipped = True
                    break
                if flipped:
                    break
            if not flipped:
                break
    return np.array(tri, np.int32)


def surround_triangles(
    vertices: np.ndarray, size: tuple[int, int], *, mouth: np.ndarray | None = None, mouth_inside: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The triangulation over feature points and anchors, in parts that meet along the image's edge,
    the mouth opening's outline an edge of it.

    Parameters
    ----------
    vertices : (P, 2) float, px
        Feature points then :func:`surround_anchors`' anchors (the outer rectangle last, beyond the
        image; the other points inside it or on its edge), in the standard geometry (mouth open).
    size : (W, H)
    mouth : (m,) int, optional
        The mouth opening's outline (the teeth subregion's polygon: the inner lips), in order.
    mouth_inside : (k,) int, optional
        The points inside it (the teeth points).

    Returns
    -------
    triangles : (K, 3) int32
        The Delaunay triangles of the points inside the image (its edge included), with the mouth
        outline's edges made triangle edges (:func:`constrain`), those inside the outline first;
        then those of the points on the image's edge and beyond that lie outside the image. No
        triangle joins a point inside the mouth to one outside it, so a closed mouth folds the
        opening away without dragging the teeth across the lips.
    mouth_triangles : (K,) bool
        The triangles inside the outline.
    """
    from stages.synthesis.warp import triangulate

    vertices = np.asarray(vertices, np.float64)
    W, H = size
    lo, hi = np.array([-0.5, -0.5]), np.array([W - 0.5, H - 0.5])
    eps = 1e-6
    within = np.all((vertices >= lo - eps) & (vertices <= hi + eps), axis=1)
    on_edge = np.any((np.abs(vertices - lo) < eps) | (np.abs(vertices - hi) < eps), axis=1)
    inner = np.flatnonzero(within)
    face = inner[triangulate(vertices[inner])]
    opening = np.zeros(len(face), bool)
    if mouth is not None and len(mouth) >= 3:
        outline = list(np.asarray(mouth, np.int64))
        face = constrain(face, vertices, list(zip(outline, outline[1:] + outline[:1])))
        opening = _inside_polygon(vertices[face].mean(1), vertices[outline])
    outer = np.flatnonzero(on_edge | ~within)
    around = outer[triangulate(vertices[outer])]
    around = around[~np.all((vertices[around].mean(1) > lo) & (vertices[around].mean(1) < hi), axis=1)]
    triangles = np.concatenate([face[opening], face[~opening], around]).astype(np.int32)
    return triangles, np.arange(len(triangles)) < int(opening.sum())


def head_matte(points: np.ndarray, face: np.ndarray, size: tuple[int, int], head_scale: np.ndarray | None = None) -> np.ndarray:
    """``(H, W) float32`` in [0, 1]: the inside of the head ring (the hull of the face points
    ``points[face]`` scaled by ``head_scale (N,)`` at each hull point, ``RING_SCALES[0]`` when omitted) in
    the standard geometry, its edge blurred by a Gaussian of ``HEAD_MATTE_SOFTNESS`` times the
    face's radius."""
    import cv2

    W, H = size
    points = np.asarray(points, np.float64)
    ring_idx, centre = head_ring(points, face)
    outline = points[ring_idx]
    scale = np.full(len(ring_idx), RING_SCALES[0]) if head_scale is None else np.asarray(head_scale, np.float64)[ring_idx]
    polygon = centre + scale[:, None] * (outline - centre)
    shift = 4
    mask = np.zeros((H, W), np.float32)
    cv2.fillPoly(mask, [np.round(polygon * (1 << shift)).astype(np.int32)], 1.0, cv2.LINE_AA, shift)
    radius = np.sqrt(((outline - centre) ** 2).sum(1).mean())
    sigma = max(HEAD_MATTE_SOFTNESS * radius, 0.5)
    return np.clip(cv2.GaussianBlur(mask, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE), 0.0, 1.0)


def anchor_depth(
    lifted: np.ndarray, points: np.ndarray, anchors: np.ndarray, kind: np.ndarray, hull: np.ndarray, outline: np.ndarray
) -> np.ndarray:
    """Camera depth of each anchor, mm (module docstring).

    Parameters
    ----------
    lifted : (N, 3) float, mm
        The feature points of the standard geometry in the camera frame (lifted at the target
        model's depths).
    points : (N, 2) float, px
        The same points in the image.
    anchors, kind, hull : (A, 2), (A,), (A,) from :func:`surround_anchors`
    outline : (h,) int, the face outline's points (:func:`head_ring`)

    Returns
    -------
    (A,) float64, mm: a ring point ``(s - 1) r`` behind the hull point it is scaled from (``s`` its
    distance from the hull's centroid over its hull point's); the border at the outer ring's
    largest depth (a background plane just behind the head: a render of the mesh at rest
    reproduces its texture, and a triangle from the face to the border does not reach so far back
    that perspective bends its texture).
    """
    lifted = np.asarray(lifted, np.float64)
    points = np.asarray(points, np.float64)
    anchors = np.asarray(anchors, np.float64)
    ring_idx = np.asarray(outline, np.int64)
    xy = lifted[ring_idx, :2]
    radius = np.sqrt(((xy - xy.mean(0)) ** 2).sum(1).mean())
    centre = points[ring_idx].mean(0)
    ring = kind != BORDER
    scale = np.linalg.norm(anchors[ring] - centre, axis=1) / np.maximum(np.linalg.norm(points[hull[ring]] - centre, axis=1), 1e-9)
    depth = np.empty(len(kind))
    depth[ring] = lifted[hull[ring], 2] + (scale - 1.0) * radius
    outer = kind == RING_OUTER
    far = depth[outer].max() if outer.any() else lifted[ring_idx, 2].max() + (RING_SCALES[1] - 1.0) * radius
    depth[~ring] = max(far, lifted[ring_idx, 2].max() + (RING_SCALES[1] - 1.0) * radius)
    return depth


def motion_weights(kind: np.ndarray) -> np.ndarray:
    """``(A,) float64``: how much each anchor follows the head: 1 on the head ring, 0 elsewhere."""
    return (np.asarray(kind) == RING_HEAD).astype(np.float64)
