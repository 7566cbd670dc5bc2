"""The bundle types of the synthesis stages (:mod:`runner.bundle`, docs/synthesis.md).

T is the frame count, S the subregions, M the example images.
"""

from __future__ import annotations

from runner.bundle import BundleType, Field

SYNTHESIS_MODEL = BundleType(
    "synthesis_model",
    "The target's synthesis model of synthesis.build (Sec. 5-8): the examples aligned to the "
    "standard geometry, the subregions and their blending; the fields the other stages rely on.",
    (
        Field("size", "iu", (2,), "px", "(W, H) of the pack's images"),
        Field("point_names", "U", ("N",), "", "layout point names"),
        Field("standard_points", "f", ("N", 2), "px", "the standard geometry"),
        Field("neutral_points", "f", ("N", 2), "px", "the neutral geometry"),
        Field("triangles", "iu", ("F", 3), "", "the warp's triangles (vertex indices)"),
        Field("subregion_names", "U", ("S",), "", "subregion names"),
        Field("subregion_teeth", "b", ("S",), "", "the subregions synthesized from the teeth examples"),
        Field("example_names", "U", ("M",), "", "example image names"),
    ),
)

SYNTHESIS_COEFFS = BundleType(
    "synthesis_coeffs",
    "The per-subregion combination coefficients of each synthesized frame (Sec. 6, eq. 3).",
    (Field("coeffs", "f", ("T", "S", "M"), "", "coefficients of the examples per subregion"),),
)

COEFFICIENTS = BundleType(
    "coefficients",
    "The synthesis coefficients with the names of their subregions and examples.",
    (
        Field("coeff", "f", ("T", "S", "M"), "", "coefficients of the examples per subregion"),
        Field("subregions", "U", ("S",), "", "subregion names"),
        Field("examples", "U", ("M",), "", "example image names"),
    ),
)
