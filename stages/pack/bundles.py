"""The bundles of an actor pack (docs/architecture.md, "Packs in the graph") and the objects they stand for, both ways.

``pack.load`` (:mod:`stages.pack.stage`) splits a loaded :class:`stages.actor_pack.ActorPack`
into five bundles so that each stage's cache key covers exactly the part it reads:

===============  ==================  =========================================================
port             type                keys
===============  ==================  =========================================================
``layout``       ``layout``          ``name ()`` str, ``document ()`` str: the layout as JSON
                                     in the layout file's schema (names, not indices)
``geometry``     ``pack_geometry``   ``names (N,)``, ``neutral (N, 2)`` px, ``captured (K, N, 2)``
                                     px, ``examples (E, N, 2)`` px (the example expressions'
                                     points), ``size (2,)`` ``[W, H]``
``images``       ``pack_images``     ``pack ()`` name, ``names (N,)``, ``size (2,)``,
                                     ``{neutral,standard}_{image,points,name,matte}``,
                                     ``{examples,teeth}_{images,points,names,mattes}``,
                                     ``source_scale ()`` (pack px per footage px, NaN:
                                     not from footage)
``model3d``      ``pack_model3d``    ``names (N,)``, ``xyz (N, 3)`` mm, head frame (Sec. 12.1)
``camera``       ``camera``          ``intrinsics (3, 3)`` (A of eq. 10, px), ``size (2,)``
===============  ==================  =========================================================

Images are ``(H, W, 3)`` uint8 RGB, validity mattes ``(H, W)`` uint8 (255 = a real pixel; a pack
image without a matte file gets 255 everywhere); points are in px, x right, y down, origin at the centre of
the top-left pixel, rows in layout order. A bundle holds no file path, so moving a pack folder
changes no key. The ``*_from_bundle`` functions check the keys and shapes and raise
``ValueError`` naming the key; stages turn that into ``StageError`` naming their input. The
five types, as the runner checks them, are declared in :mod:`stages.pack.bundle_types`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from runner.stage import StageError
from stages.actor_pack import ActorPack, Expression
from stages.layout import Layout, parse_layout

Bundle = Mapping[str, np.ndarray]


def _field(bundle: Bundle, key: str, what: str, shape: tuple[int | None, ...] | None = None, dtype: Any = None) -> np.ndarray:
    """``bundle[key]`` as an array of ``dtype``; ValueError when it is missing or of another shape
    (``None`` in ``shape``: any length on that axis)."""
    if key not in bundle:
        raise ValueError(f"{what} bundle: expected key {key!r}, got keys {sorted(bundle)}")
    value = np.asarray(bundle[key]) if dtype is None else np.asarray(bundle[key], dtype=dtype)
    if shape is not None and (value.ndim != len(shape) or any(s is not None and s != v for s, v in zip(shape, value.shape))):
        expected = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{what} bundle: key {key!r}: expected shape {expected}, got {value.shape}")
    return value


def _names(bundle: Bundle, what: str) -> tuple[str, ...]:
    return tuple(str(n) for n in _field(bundle, "names", what, (None,)))


def _size(bundle: Bundle, what: str) -> tuple[int, int]:
    w, h = (int(v) for v in _field(bundle, "size", what, (2,)))
    return w, h


# -- layout ---------------------------------------------------------------------------------------


def layout_document(layout: Layout) -> dict[str, Any]:
    """The mapping of a layout file (schema of ``stages/layouts/zhang134.yaml``) that
    :func:`stages.layout.parse_layout` turns back into ``layout``."""
    names = layout.point_names

    def named(indices: tuple[int, ...]) -> list[str]:
        return [names[i] for i in indices]

    return {
        "name": layout.name,
        "points": list(names),
        "subregions": [
            {"name": s.name, "polygon": named(s.polygon), "points": named(s.points), "teeth": s.teeth} for s in layout.subregions
        ],
        "no_blend": [list(pair) for pair in layout.no_blend],
        "feature_point_sets": [{"name": f.name, "level": f.level, "points": named(f.points)} for f in layout.feature_point_sets],
        "rigid": named(layout.rigid),
        "tracked": named(layout.tracked),
    }


def layout_to_bundle(layout: Layout) -> dict[str, np.ndarray]:
    """The ``layout`` bundle: ``name ()`` and ``document ()``, canonical JSON (sorted keys), so
    that equal layouts give equal bundles whatever the file's comments or formatting."""
    document = json.dumps(layout_document(layout), sort_keys=True, separators=(",", ":"))
    return {"name": np.array(layout.name), "document": np.array(document)}


def layout_from_bundle(bundle: Bundle) -> Layout:
    """The :class:`Layout` of a ``layout`` bundle, validated as a layout file is."""
    text = str(_field(bundle, "document", "layout", ()))
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"layout bundle: key 'document': expected JSON, got a parse error ({exc})") from None
    try:
        return parse_layout(data, source="bundle")
    except StageError as exc:
        raise ValueError(str(exc)) from None


# -- geometry, 3D model, camera ------------------------------------------------------------------


def geometry_to_bundle(pack: ActorPack) -> dict[str, np.ndarray]:
    """The ``pack_geometry`` bundle: the neutral, captured and example feature points (Sec. 10, 14)."""
    return {
        "names": np.array(pack.layout.point_names),
        "neutral": np.asarray(pack.neutral.points, np.float64),
        "captured": np.asarray(pack.captured_points, np.float64),
        "examples": np.stack([np.asarray(e.points, np.float64) for e in pack.examples]),
        "size": np.array(pack.image_size, np.int64),
    }


@dataclass(frozen=True)
class PackGeometry:
    """A ``pack_geometry`` bundle read back: point ``names (N,)``, ``neutral (N, 2)`` px,
    ``captured (K, N, 2)`` px, ``examples (E, N, 2)`` px, ``size`` ``(W, H)``."""

    names: tuple[str, ...]
    neutral: np.ndarray
    captured: np.ndarray
    examples: np.ndarray
    size: tuple[int, int]

    def rows(self, names: Any) -> list[int]:
        """Row indices of the points ``names``; ValueError naming the first one missing."""
        return _rows(self.names, names, "pack_geometry")


def geometry_from_bundle(bundle: Bundle) -> PackGeometry:
    """:class:`PackGeometry` of a ``pack_geometry`` bundle (keys and shapes checked)."""
    names = _names(bundle, "pack_geometry")
    n = len(names)
    return PackGeometry(
        names,
        _field(bundle, "neutral", "pack_geometry", (n, 2), np.float64),
        _field(bundle, "captured", "pack_geometry", (None, n, 2), np.float64),
        _field(bundle, "examples", "pack_geometry", (None, n, 2), np.float64),
        _size(bundle, "pack_geometry"),
    )


def layout_and_geometry(layout: Bundle, geometry: Bundle) -> tuple[Layout, PackGeometry]:
    """The layout and the ``pack_geometry`` of one pack, read back; ValueError when the geometry's
    points are not the layout's, in its order."""
    read_layout, read_geometry = layout_from_bundle(layout), geometry_from_bundle(geometry)
    if read_geometry.names != read_layout.point_names:
        raise ValueError(
            f"pack_geometry bundle: key 'names': expected the {read_layout.n_points} points of "
            f"layout {read_layout.name!r} in its order (connect one pack's layout and geometry)"
        )
    return read_layout, read_geometry


def model3d_to_bundle(pack: ActorPack) -> dict[str, np.ndarray]:
    """The ``pack_model3d`` bundle: the generic face model (Sec. 12.1), mm, head frame."""
    return {"names": np.array(pack.layout.point_names), "xyz": np.asarray(pack.model3d, np.float64)}


def model3d_from_bundle(bundle: Bundle, names: Any) -> np.ndarray:
    """The generic model ``(len(names), 3)`` mm at the points ``names`` of a ``pack_model3d``
    bundle; ValueError naming a point the model does not have."""
    model_names = _names(bundle, "pack_model3d")
    xyz = _field(bundle, "xyz", "pack_model3d", (len(model_names), 3), np.float64)
    return xyz[_rows(model_names, names, "pack_model3d")]


def camera_to_bundle(pack: ActorPack) -> dict[str, np.ndarray]:
    """The ``camera`` bundle: intrinsics A (eq. 10) and the image size they are for."""
    return {"intrinsics": np.asarray(pack.intrinsics, np.float64), "size": np.array(pack.image_size, np.int64)}


def camera_from_bundle(bundle: Bundle, *, size: tuple[int, int] | None = None) -> np.ndarray:
    """The intrinsics ``(3, 3)`` of a ``camera`` bundle; with ``size`` (the clip's ``(W, H)``),
    ValueError when the camera is for another image size."""
    intrinsics = _field(bundle, "intrinsics", "camera", (3, 3), np.float64)
    own = _size(bundle, "camera")
    if size is not None and tuple(int(v) for v in size) != own:
        raise ValueError(
            f"camera bundle: intrinsics are for {own[0]}x{own[1]} images, the clip's frames are "
            f"{size[0]}x{size[1]}; use a pack from this camera"
        )
    return intrinsics


def _rows(have: tuple[str, ...], names: Any, what: str) -> list[int]:
    where = {n: i for i, n in enumerate(have)}
    missing = [str(n) for n in names if str(n) not in where]
    if missing:
        raise ValueError(f"{what} bundle: expected points {missing[:5]}, the pack's layout has none of that name")
    return [where[str(n)] for n in names]


# -- images ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PackImages:
    """A ``pack_images`` bundle with its layout: what :func:`stages.synthesis.build.build_synthesis_model`
    reads of an actor pack (the same attribute names as :class:`ActorPack`). ``path`` is the
    pack's name, for messages (a bundle holds no file path)."""

    path: str
    layout: Layout
    image_size: tuple[int, int]
    neutral: Expression
    standard: Expression
    examples: list[Expression]
    teeth_examples: list[Expression]
    source_scale: float | None = None


def _matte(e: Expression, size: tuple[int, int]) -> np.ndarray:
    w, h = size
    return np.full((h, w), 255, np.uint8) if e.matte is None else np.asarray(e.matte, np.uint8)


def images_to_bundle(pack: ActorPack) -> dict[str, np.ndarray]:
    """The ``pack_images`` bundle: neutral, standard, examples and teeth examples (Sec. 5, 8)."""
    size = pack.image_size
    out = {
        "pack": np.array(pack.name),
        "names": np.array(pack.layout.point_names),
        "size": np.array(size, np.int64),
        "source_scale": np.float64(np.nan if pack.source_scale is None else pack.source_scale),
    }
    for key, e in (("neutral", pack.neutral), ("standard", pack.standard)):
        out |= {
            f"{key}_image": e.image,
            f"{key}_points": np.asarray(e.points, np.float64),
            f"{key}_name": np.array(e.name),
            f"{key}_matte": _matte(e, size),
        }
    w, h = size
    n = pack.layout.n_points
    for key, group in (("examples", pack.examples), ("teeth", pack.teeth_examples)):
        out[f"{key}_images"] = np.stack([e.image for e in group]) if group else np.zeros((0, h, w, 3), np.uint8)
        out[f"{key}_points"] = np.stack([np.asarray(e.points, np.float64) for e in group]) if group else np.zeros((0, n, 2))
        out[f"{key}_names"] = np.array([e.name for e in group], dtype=str)
        out[f"{key}_mattes"] = np.stack([_matte(e, size) for e in group]) if group else np.zeros((0, h, w), np.uint8)
    return out


def images_from_bundle(bundle: Bundle, layout: Layout) -> PackImages:
    """:class:`PackImages` of a ``pack_images`` bundle and its ``layout`` (keys, shapes and the
    point names checked against the layout)."""
    what = "pack_images"
    if _names(bundle, what) != layout.point_names:
        raise ValueError(
            f"{what} bundle: key 'names': expected the {layout.n_points} points of layout {layout.name!r} in its order"
        )
    w, h = _size(bundle, what)
    n = layout.n_points

    def one(key: str) -> Expression:
        return Expression(
            str(_field(bundle, f"{key}_name", what, ())),
            _field(bundle, f"{key}_image", what, (h, w, 3), np.uint8),
            _field(bundle, f"{key}_points", what, (n, 2), np.float64),
            _field(bundle, f"{key}_matte", what, (h, w), np.uint8),
        )

    def group(key: str) -> list[Expression]:
        names = [str(v) for v in _field(bundle, f"{key}_names", what, (None,))]
        m = len(names)
        images = _field(bundle, f"{key}_images", what, (m, h, w, 3), np.uint8)
        points = _field(bundle, f"{key}_points", what, (m, n, 2), np.float64)
        mattes = _field(bundle, f"{key}_mattes", what, (m, h, w), np.uint8)
        return [Expression(name, image, pts, matte) for name, image, pts, matte in zip(names, images, points, mattes)]

    scale = float(_field(bundle, "source_scale", what, ()))
    return PackImages(
        str(_field(bundle, "pack", what, ())),
        layout,
        (w, h),
        one("neutral"),
        one("standard"),
        group("examples"),
        group("teeth"),
        None if np.isnan(scale) else scale,
    )


def pack_to_bundles(pack: ActorPack) -> dict[str, dict[str, np.ndarray]]:
    """All five bundles of ``pack``, by ``pack.load``'s port name."""
    return {
        "layout": layout_to_bundle(pack.layout),
        "geometry": geometry_to_bundle(pack),
        "images": images_to_bundle(pack),
        "model3d": model3d_to_bundle(pack),
        "camera": camera_to_bundle(pack),
    }
