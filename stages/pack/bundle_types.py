"""The bundle types ``pack.load`` splits an actor pack into (:mod:`runner.bundle`); the functions
that build and read them are in :mod:`stages.pack.bundles`.

N is the layout's points; images ``(H, W, 3)`` uint8 RGB, validity mattes ``(H, W)`` uint8 (255 =
a real pixel); points px, x right, y down, rows in layout order.
"""

from __future__ import annotations

from runner.bundle import BundleType, Field

SIZE = Field("size", "iu", (2,), "px", "(W, H) of the pack's images")

LAYOUT = BundleType(
    "layout",
    "A layout: feature points, subregions, rigid points (read back with layout_from_bundle).",
    (
        Field("name", "U", (), "", "the layout's name"),
        Field("document", "U", (), "", "the layout as canonical JSON (sorted keys) in the layout file's schema"),
    ),
)

PACK_GEOMETRY = BundleType(
    "pack_geometry",
    "The pack's geometries: neutral, captured (Sec. 10, 14) and the example expressions' points.",
    (
        Field("names", "U", ("N",), "", "layout point names"),
        Field("neutral", "f", ("N", 2), "px", "the neutral geometry"),
        Field("captured", "f", ("K", "N", 2), "px", "the captured geometries"),
        Field("examples", "f", ("E", "N", 2), "px", "the example expressions' points"),
        SIZE,
    ),
)

PACK_IMAGES = BundleType(
    "pack_images",
    "The pack's images with their points: neutral, standard, examples and teeth examples (Sec. 5, 6, 8).",
    (
        Field("pack", "U", (), "", "the pack's name"),
        Field("names", "U", ("N",), "", "layout point names"),
        SIZE,
        Field("source_scale", "f", (), "", "pack px per footage px (NaN: not from footage)"),
        *(
            f
            for key in ("neutral", "standard")
            for f in (
                Field(f"{key}_image", "u", ("H", "W", 3), "", f"the {key} image, RGB"),
                Field(f"{key}_points", "f", ("N", 2), "px", f"the {key} image's points"),
                Field(f"{key}_name", "U", (), "", f"the {key} image's name"),
                Field(f"{key}_matte", "u", ("H", "W"), "", f"the {key} image's validity matte"),
            )
        ),
        *(
            f
            for key, count in (("examples", "M"), ("teeth", "M2"))
            for f in (
                Field(f"{key}_images", "u", (count, "H", "W", 3), "", f"the {key} images, RGB"),
                Field(f"{key}_points", "f", (count, "N", 2), "px", f"the {key} images' points"),
                Field(f"{key}_names", "U", (count,), "", f"the {key} images' names"),
                Field(f"{key}_mattes", "u", (count, "H", "W"), "", f"the {key} images' validity mattes"),
            )
        ),
    ),
)

PACK_MODEL3D = BundleType(
    "pack_model3d",
    "The generic 3D face model at the layout's points, in the head frame (Sec. 12.1).",
    (
        Field("names", "U", ("N",), "", "layout point names"),
        Field("xyz", "f", ("N", 3), "mm", "model points"),
    ),
)

CAMERA = BundleType(
    "camera",
    "The camera of the pack's images.",
    (
        Field("intrinsics", "f", (3, 3), "px", "the matrix A of eq. 10"),
        SIZE,
    ),
)
