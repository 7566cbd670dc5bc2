"""The bundle types of the pack-building stages (:mod:`runner.bundle`, docs/packbuild.md)."""

from __future__ import annotations

from runner.bundle import BundleType, Field

FRAME_FILTER = BundleType(
    "frame_filter",
    "The frames pack.filter found usable, with the reason each other frame was rejected.",
    (
        Field("keep", "b", ("T",), "", "usable frames"),
        Field("cause_names", "U", ("C",), "", "the reasons a frame is rejected"),
    ),
)
PACK_SELECTION = BundleType(
    "pack_selection",
    "The frames pack.select chose for the pack's images (frame indices into the footage).",
    (
        Field("neutral", "iu", (), "", "the neutral's frame"),
        Field("standard", "iu", (), "", "the standard image's frame"),
        Field("examples", "iu", ("E",), "", "the example expressions' frames"),
        Field("teeth", "iu", ("*",), "", "the teeth examples' frames"),
        Field("captured", "iu", ("K",), "", "the captured geometries' frames"),
        Field("to_pack", "f", ("T", 4), "", "per frame the similarity frame -> pack image (a, b, tx, ty; tx, ty px)"),
        Field("size", "iu", (2,), "px", "(W, H) of the pack's images"),
        Field(
            "example_radius_px", "f", (), "px", "coverage radius of the examples over the candidate frames (RMS point distance)"
        ),
        Field("captured_radius_px", "f", (), "px", "coverage radius of the captured set over the candidate frames"),
        Field("warnings", "U", ("*",), "", "what the selection could not do as asked"),
    ),
)
PHOTO_IDENTITY = BundleType(
    "photo_identity",
    "Photos whose face shape (rigid landmark proportions) differs from the majority's.",
    (
        Field("names", "U", ("T",), "", "the photos' names, one per frame"),
        Field("distance", "f", ("T",), "", "face-shape distance to the majority's (NaN without a face)"),
        Field("differs", "b", ("T",), "", "the distance is above max_distance"),
        Field("max_distance", "f", (), "", "the threshold it was judged with"),
    ),
)
