"""The bundle type of ``report.sheet`` (:mod:`runner.bundle`, docs/report.md).

K is the contact sheet's frames.
"""

from __future__ import annotations

from runner.bundle import BundleType, Field

SHEET = BundleType(
    "sheet",
    "The report's contact sheet: performer | result JPEGs of chosen frames.",
    (
        Field("frame", "iu", ("K",), "", "the sheet's frame indices"),
        Field("label", "U", ("K",), "", "each frame's label"),
        Field("jpeg", "u", ("*",), "", "the K JPEGs one after the other"),
        Field("jpeg_end", "iu", ("K",), "", "byte offset where each JPEG ends"),
        Field("frames", "iu", (), "", "the clip's frame count T"),
        Field("fps", "f", (), "Hz", "frames per second of the clip"),
        Field("performer_size", "iu", (2,), "px", "(W, H) of the performer's frames"),
        Field("result_size", "iu", (2,), "px", "(W, H) of the result's frames"),
    ),
)
