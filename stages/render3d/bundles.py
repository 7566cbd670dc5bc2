"""The bundle type of ``render3d.head`` (:mod:`runner.bundle`, docs/render3d.md)."""

from __future__ import annotations

from runner.bundle import BundleType, Field

HEAD3D = BundleType(
    "head3d",
    "The performer's head motion as a rigid motion of the target mesh into the camera.",
    (
        Field("R", "f", ("T", 3, 3), "", "rotation, target mesh -> camera"),
        Field("t", "f", ("T", 3), "mm", "translation, target mesh -> camera"),
        Field("valid", "b", ("T",), "", "frames with a pose"),
        Field("ypr_deg", "f", ("T", 3), "deg", "yaw, pitch, roll"),
        Field("pivot", "f", (3,), "mm", "the point the head turns about"),
    ),
)
