"""The bundle type of ``occlusion.detect`` (:mod:`runner.bundle`, docs/occlusion.md).

T is the frame count, R the face regions, N the points.
"""

from __future__ import annotations

from runner.bundle import BundleType, Field

OCCLUSION = BundleType(
    "occlusion",
    "Occluded face regions per frame.",
    (
        Field("regions", "U", ("R",), "", "mouth, eye_l, eye_r, brow_l, brow_r, nose (_l = image left)"),
        Field("occluded", "b", ("T", "R"), "", "the region is occluded (score below the stage's threshold)"),
        Field(
            "score",
            "f",
            ("T", "R"),
            "",
            "visibility of the region's structure: 1 as in the clip's typical frame, NaN where not judged",
        ),
        Field("region_points", "b", ("R", "N"), "", "the points each region covers, over names"),
        Field("names", "U", ("N",), "", "layout point names"),
        Field("valid", "b", ("T",), "", "frames judged"),
    ),
)
