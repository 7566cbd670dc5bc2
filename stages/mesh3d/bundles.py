"""The bundle type of ``mesh3d.synthesize`` (:mod:`runner.bundle`, docs/render3d.md).

T is the frame count, N the mesh's vertices (the layout's points), F its triangles.
"""

from __future__ import annotations

from runner.bundle import BundleType, Field

MESH3D = BundleType(
    "mesh3d",
    "The target's synthesized 3D face mesh per frame (Sec. 9 synthesis in the target head frame).",
    (
        Field("vertices", "f", ("T", "N", 3), "mm", "synthesized vertices"),
        Field("lifted", "f", ("T", "N", 3), "mm", "the 2D target geometry lifted at the neutral's depths"),
        Field("uv", "f", ("T", "N", 2), "px", "texture coordinates into the frame's texture"),
        Field("coeffs", "f", ("T", "S", "*"), "", "the per-subregion QP coefficients"),
        Field("triangles", "iu", ("F", 3), "", "vertex indices of each triangle"),
        Field("neutral", "f", ("N", 3), "mm", "the neutral mesh"),
        Field("pivot", "f", (3,), "mm", "the point the head turns about"),
        Field("camera", "f", (3, 3), "px", "the intrinsics A of eq. 10"),
        Field("names", "U", ("N",), "", "layout point names"),
        Field("size", "iu", (2,), "px", "(W, H) of the frames"),
        Field("fps", "fiu", (), "Hz", "frames per second, when the points carry it", optional=True),
    ),
)
