"""Offline processing of an actor pack's example images (Sec. 5.2, 5.3, 7, 8).

Every example and teeth example is aligned to the standard image by the triangulation-based warp;
the standard image's subregions are rasterized into an index mask; the weight map for
fade-in/fade-out blending along subregion boundaries is computed (eq. 7), with no blending on
the layout's ``no_blend`` pairs (natural colour edges: eye outlines, outer lip line).

The result is a *synthesis model* bundle (port type ``synthesis_model``), a dict of arrays:

=====================  ==================  =====================================================
key                    shape, dtype        meaning
=====================  ==================  =====================================================
``size``               (2,) int64          (W, H) of every image, px
``standard_points``    (N, 2) f8           the standard geometry (all examples aligned to it)
``anchors``            (A, 2) f8           anchor points around the face (:mod:`stages.synthesis.surround`:
                                           head ring, outer ring, border; appended to every point set)
``anchor_kind``        (A,) i1             ``RING_HEAD`` 1, ``RING_OUTER`` 2, ``BORDER`` 0
``anchor_hull``        (A,) i8             the feature point a ring anchor is scaled from (-1: border)
``face_outline``       (h,) i8             the face outline: the hull of the feature points but the teeth
``triangles``          (K, 3) i4           triangulation over standard points + anchors
``mouth_triangles``    (K,) bool           the triangles of the mouth opening (first in order)
``examples``           (M, H, W, 3) u1     example expressions aligned to the standard image
``example_points``     (M, N, 2) f8        their own geometry G_i (the QP uses it, Sec. 6)
``teeth``              (Mt, H, W, 3) u1    teeth examples aligned to the standard image (Sec. 8)
``teeth_points``       (Mt, N, 2) f8       their geometry
``standard``           (H, W, 3) u1        the standard image
``outside``            (H, W, 3) u1        the neutral image aligned to the standard geometry: the
                                           composite outside the face (hair, neck, background)
``valid``              (H, W) f4           validity matte of the composite in the standard geometry:
                                           the least of the aligned images' mattes (1 = real pixels)
``head_matte``         (H, W) f4           the head region in the standard geometry (surround)
``neutral``            (H, W, 3) u1        the neutral image, unaligned (``warp-only`` mode)
``neutral_valid``      (H, W) f4           its validity matte
``neutral_points``     (N, 2) f8           its geometry
``region``             (H, W) i2           subregion index per pixel, S = outside the face
``blend_r``            (H, W) f4           eq. 7: weight r/255 of subregion i1, in [0.5, 1]
``blend_i1``           (H, W) i2           eq. 7: the pixel's own subregion (= region)
``blend_i2``           (H, W) i2           eq. 7: the neighbouring subregion (= i1 off the bands)
``subregion_points``   (S, N) bool         membership of each point in G^R (polygon + inside)
``subregion_teeth``    (S,) bool           the teeth subregion
``point_names``        (N,) str            the layout's feature point names (row order)
``subregion_names``    (S,) str
``example_names``      (M,) str
``teeth_names``        (Mt,) str
``teeth_host``         () i8               the face subregion the teeth subregion lies in (lips)
``teeth_polygon``      (n,) i8             the teeth subregion's outline (points, in order)
``teeth_open_area``    (2,) f8             teeth polygon area of the neutral and of the least open
                                           teeth example, px^2 (:func:`teeth_mix`)
``source_scale``       () f8               pack px per footage px (NaN: not built from footage)
=====================  ==================  =====================================================

Index ``S`` (one past the last subregion) is the *outside* of the face (hair, background),
taken from the neutral image aligned to the standard geometry (not the standard image itself:
its jaw is dropped furthest, and the edge of that jaw, which lies just outside the face
outline's points, would show as a second chin line below the synthesized face in every frame
whose mouth is less open); it takes part in blending like a subregion.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from runner.stage import Context, Param, SequenceStage, StageError
from stages.pack.bundle_types import LAYOUT, PACK_IMAGES
from stages.synthesis.bundles import SYNTHESIS_MODEL
from stages.actor_pack import ActorPack, Expression
from stages.layout import Layout, subregion_mask
from stages.pack.bundles import images_from_bundle, layout_from_bundle
from stages.synthesis.surround import head_extent, head_matte, head_ring, surround_anchors, surround_triangles
from stages.synthesis.warp import warp_images

__all__ = [
    "blend_weight_map",
    "subregion_weights",
    "align_to_standard",
    "polygon_area",
    "teeth_host",
    "build_synthesis_model",
    "BuildSynthesis",
]


def blend_weight_map(
    region: np.ndarray, *, n_labels: int, band_px: float, no_blend: set[tuple[int, int]]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The weight map of Sec. 7: fade-in/fade-out bands along subregion boundaries (eq. 7).

    A pixel of subregion ``i1`` within ``band_px / 2`` of the boundary with a neighbouring
    subregion ``i2`` gets ``r = 1/2 + d / band_px`` (``d`` its distance to the boundary, px), so
    the weights of the two sides meet at 1/2 on the boundary and reach 1 at the edge of the band:
    the blended colour ``r I_i1 + (1 - r) I_i2`` is continuous across the boundary. ``i2`` is the
    nearest subregion whose pair with ``i1`` is not in ``no_blend``; pixels with none within the
    band get ``r = 1, i2 = i1``. Where three subregions meet, only the nearest neighbour takes
    part (eq. 7 stores two indices per pixel).

    Parameters
    ----------
    region : (H, W) int array
        Label per pixel in ``[0, n_labels)``.
    n_labels : int
    band_px : float
        Full width of the blending band, px (0 disables blending).
    no_blend : set of (int, int)
        Unordered label pairs not blended.

    Returns
    -------
    r : (H, W) float32 in [0.5, 1]
        The R channel of the paper's weight map divided by 255.
    i1, i2 : (H, W) int16
        The G and B channels: the pixel's own label and its blending partner.
    """
    import cv2

    H, W = region.shape
    i1 = region.astype(np.int16)
    r = np.ones((H, W), np.float32)
    i2 = i1.copy()
    if band_px <= 0:
        return r, i1, i2
    allowed = np.ones((n_labels, n_labels), bool)
    np.fill_diagonal(allowed, False)
    for a, b in no_blend:
        allowed[a, b] = allowed[b, a] = False
    best = np.full((H, W), np.inf, np.float32)
    for label in range(n_labels):
        outside = (region != label).astype(np.uint8)
        if outside.all():
            continue
        dist = cv2.distanceTransform(outside, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)  # to the nearest pixel of label
        dist = np.where(allowed[region, label], dist, np.inf)
        closer = dist < best
        best[closer] = dist[closer]
        i2[closer] = label
    d = best - 0.5  # pixel centres of the two sides are 1 apart: the boundary lies half way
    band = d < band_px / 2
    r[band] = 0.5 + d[band] / band_px
    i2[~band] = i1[~band]
    return r, i1, i2


def subregion_weights(r: np.ndarray, i1: np.ndarray, i2: np.ndarray, *, n_labels: int) -> np.ndarray:
    """The per-subregion weight tensor equivalent to the eq. 7 encoding (for tests and docs).

    ``w[s, y, x] = r [i1 == s] + (1 - r) [i2 == s]``; ``sum_s w[s] = 1`` everywhere.

    Returns
    -------
    (n_labels, H, W) float32
    """
    labels = np.arange(n_labels)[:, None, None]
    return (r * (i1 == labels) + (1 - r) * (i2 == labels)).astype(np.float32)


def align_to_standard(
    images: np.ndarray,
    points: np.ndarray,
    standard_points: np.ndarray,
    anchors: np.ndarray,
    triangles: np.ndarray,
    *,
    device: str = "cpu",
    padding_mode: str = "border",
) -> np.ndarray:
    """Align example images to the standard geometry (Sec. 5.2).

    Parameters
    ----------
    images : (M, H, W, C) uint8 (colour, or validity mattes with ``padding_mode="zeros"``: a
        position outside the source image is not a real pixel)
    points : (M, N, 2) float, px, each image's feature points
    standard_points : (N, 2) float, px
    anchors : (A, 2) float, px, fixed border anchors
    triangles : (K, 3) int, over standard points + anchors

    Returns
    -------
    (M, H, W, C) uint8, each image warped so that its points land on ``standard_points``.
    """
    import torch

    M = len(images)
    if M == 0:
        return images.copy()
    src = torch.from_numpy(np.concatenate([points, np.broadcast_to(anchors, (M,) + anchors.shape)], 1)).to(device)
    dst = torch.from_numpy(np.concatenate([standard_points, anchors])).to(device)[None].expand(M, -1, -1)
    batch = torch.from_numpy(images).to(device).permute(0, 3, 1, 2).float()
    out = warp_images(batch, src, dst, triangles, padding_mode=padding_mode)
    return out.round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()


def polygon_area(points: np.ndarray) -> np.ndarray:
    """Area of polygons ``(..., n, 2)`` px (shoelace formula, absolute), ``(...)`` px^2."""
    x, y = points[..., 0], points[..., 1]
    return 0.5 * np.abs(np.sum(x * np.roll(y, -1, axis=-1) - np.roll(x, -1, axis=-1) * y, axis=-1))


def teeth_host(layout: Layout) -> int:
    """Index of the face subregion holding most of the teeth polygon's points (the lips), -1 if none."""
    teeth = layout.teeth_subregion
    if teeth is None:
        return -1
    outline = set(teeth.polygon)
    shared = [len(outline & set(s.all_points)) if not s.teeth else -1 for s in layout.subregions]
    return int(np.argmax(shared)) if max(shared) > 0 else -1


def build_synthesis_model(
    pack: ActorPack,
    *,
    band_px: float = 10.0,
    anchors_per_side: int = 4,
    anchor_margin: float = 0.25,
    device: str = "cpu",
) -> dict[str, np.ndarray]:
    """Offline processing of an :class:`stages.actor_pack.ActorPack` into a synthesis model bundle.

    See the module docstring for the keys. ``band_px`` is the full width of the blending bands;
    anchors lie ``anchor_margin`` (fraction of the larger image side) outside the image so that
    the runtime warp covers the whole frame under head motion.
    """
    layout: Layout = pack.layout
    size = tuple(int(v) for v in pack.image_size)
    S = len(layout.subregions)
    std = np.asarray(pack.standard.points, np.float64)
    face_points = np.array([not any(i in s.points for s in layout.subregions if s.teeth) for i in range(layout.n_points)])
    head_scale = head_extent(pack.neutral.image, np.asarray(pack.neutral.points, np.float64), face_points)
    anchors, anchor_kind, anchor_hull = surround_anchors(
        std, size, face=face_points, per_side=anchors_per_side, margin=anchor_margin, head_scale=head_scale
    )
    region = subregion_mask(layout, std, size).astype(np.int16)
    region[region < 0] = S
    if not (region < S).any():
        raise StageError(f"actor pack {pack.path}: field 'standard.points': the subregion polygons cover no pixel")
    teeth = layout.teeth_subregion
    vertices = np.concatenate([std, anchors])
    triangles, mouth_triangles = surround_triangles(
        vertices,
        size,
        mouth=None if teeth is None else list(teeth.polygon),
        mouth_inside=None if teeth is None else list(teeth.points),
    )
    names = [s.name for s in layout.subregions]
    no_blend = {(names.index(a), names.index(b)) for a, b in layout.no_blend}
    r, i1, i2 = blend_weight_map(region, n_labels=S + 1, band_px=band_px, no_blend=no_blend)
    membership = np.zeros((S, layout.n_points), bool)
    for k, s in enumerate(layout.subregions):
        membership[k, list(s.all_points)] = True

    W, H = size

    def matte(e: Expression) -> np.ndarray:
        return np.full((H, W), 255, np.uint8) if e.matte is None else np.asarray(e.matte, np.uint8)

    def stack(expressions: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if not expressions:
            return np.zeros((0, H, W, 3), np.uint8), np.zeros((0, layout.n_points, 2)), np.zeros((0, H, W), np.uint8)
        pts = np.stack([np.asarray(e.points, np.float64) for e in expressions])
        imgs = np.stack([e.image for e in expressions])
        mattes = align_to_standard(
            np.stack([matte(e) for e in expressions])[..., None],
            pts,
            std,
            anchors,
            triangles,
            device=device,
            padding_mode="zeros",
        )[..., 0]
        return align_to_standard(imgs, pts, std, anchors, triangles, device=device), pts, mattes

    examples, example_points, example_mattes = stack(pack.examples)
    teeth_images, teeth_points, teeth_mattes = stack(pack.teeth_examples)
    outside, _, outside_matte = stack([pack.neutral])
    if teeth is not None and len(teeth_images) == 0:
        raise StageError(
            f"actor pack {pack.path}: field 'teeth_examples': the layout has a teeth subregion but the pack no teeth examples"
        )
    # real where the images that make the pixel are: the outside image outside the face, every example and
    # teeth example inside it (the face alpha 1 - w_S of eq. 7 weighs the two)
    alpha = 1.0 - subregion_weights(r, i1, i2, n_labels=S + 1)[S]
    inside = np.concatenate([example_mattes, teeth_mattes]).min(0).astype(np.float32) / 255.0
    valid = (alpha * inside + (1.0 - alpha) * outside_matte[0].astype(np.float32) / 255.0).astype(np.float32)
    if teeth is not None:
        outline = list(teeth.polygon)
        open_area = [
            float(polygon_area(np.asarray(pack.neutral.points, np.float64)[outline])),
            float(polygon_area(teeth_points[:, outline]).min()),
        ]
    else:
        open_area = [0.0, 0.0]
    return {
        "size": np.array(size, np.int64),
        "standard_points": std,
        "anchors": anchors,
        "anchor_kind": anchor_kind,
        "anchor_hull": anchor_hull,
        "face_outline": head_ring(std, face_points)[0],
        "triangles": triangles.astype(np.int32),
        "mouth_triangles": mouth_triangles,
        "examples": examples,
        "example_points": example_points,
        "teeth": teeth_images,
        "teeth_points": teeth_points,
        "standard": np.ascontiguousarray(pack.standard.image),
        "outside": outside[0],
        "valid": valid,
        "head_matte": head_matte(std, face_points, size, head_scale),
        "neutral": np.ascontiguousarray(pack.neutral.image),
        "neutral_valid": matte(pack.neutral).astype(np.float32) / 255.0,
        "neutral_points": np.asarray(pack.neutral.points, np.float64),
        "region": region,
        "blend_r": r,
        "blend_i1": i1,
        "blend_i2": i2,
        "subregion_points": membership,
        "subregion_teeth": np.array([s.teeth for s in layout.subregions], bool),
        "point_names": np.array(layout.point_names),
        "subregion_names": np.array(names),
        "example_names": np.array([e.name for e in pack.examples]),
        "teeth_names": np.array([e.name for e in pack.teeth_examples]),
        "teeth_host": np.int64(teeth_host(layout)),
        "teeth_polygon": np.array(list(teeth.polygon) if teeth is not None else [], np.int64),
        "teeth_open_area": np.array(open_area),
        "source_scale": np.float64(np.nan if pack.source_scale is None else pack.source_scale),
    }


class BuildSynthesis(SequenceStage):
    """``synthesis.build``: align an actor pack's examples, rasterize subregions, make the weight map.

    Takes ``pack.load``'s ``layout`` and ``images`` (:class:`stages.pack.bundles.PackImages`
    stands in for the :class:`ActorPack` of :func:`build_synthesis_model`)."""

    name = "synthesis.build"
    version = "5"
    doc = "offline: align examples and teeth examples to the standard image, subregion mask, blend weight map"
    inputs = {"layout": LAYOUT, "images": PACK_IMAGES}
    outputs = {"model": SYNTHESIS_MODEL}
    params = (
        Param(
            "band_px",
            float,
            10.0,
            "full width of the fade-in/fade-out band along subregion boundaries, px (Sec. 7)",
            min=0.0,
            max=1000.0,
        ),
        Param("anchors_per_side", int, 4, "border anchor points per image side for the triangulation warp", min=1, max=64),
        Param("anchor_margin", float, 0.25, "anchor rectangle outside the image, fraction of the larger side", min=0.0, max=10.0),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        try:
            pack = images_from_bundle(inputs["images"], layout_from_bundle(inputs["layout"]))
        except ValueError as exc:
            raise StageError(f"{self.name}: {exc}") from None
        model = build_synthesis_model(
            pack,
            band_px=params["band_px"],
            anchors_per_side=params["anchors_per_side"],
            anchor_margin=params["anchor_margin"],
            device=ctx.device,
        )
        return {"model": model}
