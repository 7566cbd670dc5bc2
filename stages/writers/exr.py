"""``write.exr``: one OpenEXR file per frame, half float, scene-linear, premultiplied RGBA.

Pixels: the synthesized frames are sRGB-encoded floats in [0, 1]; they are decoded to
scene-linear with the IEC 61966-2-1 curve (:func:`stages.color.srgb_to_linear`), so the files
hold linear light with Rec.709/sRGB primaries (``oiio:ColorSpace`` = ``lin_rec709_scene``).

Channels with the ``head_matte`` input (the shot, :func:`shot_channels`): ``R, G, B, A`` the head with
OpenEXR's *associated* alpha (A = the head matte, R, G, B = the linear colour times A), ``plate.R,
plate.G, plate.B`` the whole frame (opaque: the plate the head sits in), ``face.A`` the face matte
and ``filled.A`` how much of each pixel was filled because no real source pixel covers it — layer
names as OpenEXR's multi-layer convention (``layer.channel``) and Nuke read them (layers ``plate``,
``face``, ``filled``; ``face.A`` becomes ``face.alpha``). Without ``head_matte``: the face mask is the
alpha (R, G, B = colour times it, 0 outside the face); without a mask either, alpha is 1 and the
whole frame is kept.

Per-frame metadata goes into namespaced header attributes (``exmap:frame`` ...; see
``docs/writers.md``). Each file is written under a temporary name and renamed into place, so a
file named ``frame.%06d.exr`` is always complete. The codecs ``zip``, ``zips`` and ``none`` are
written by :mod:`stages.writers.exr_file` (numpy and zlib-ng's deflate), ``piz`` and ``rle`` by
OpenImageIO, with the same header and pixels.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from runner.stage import Context, FrameStage, Param, StageError
from stages.geometry.bundles import HEAD_POSES, SIMILARITY
from stages.render3d.bundles import HEAD3D
from stages.color import srgb_to_linear, to_unit_float
from stages.writers.atomic import atomic_write
from stages.writers.bundles import check_bundle
from stages.writers.exr_file import COMPRESSION_CODES, ZIP_LEVEL, ZIP_LEVELS, write_scanline_exr
from stages.writers.lut import apply_elementwise

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only; imported where used, so that importing this module stays light
    import OpenImageIO as oiio

COMPRESSIONS = ("zip", "zips", "piz", "rle", "none")  # OpenEXR's lossless codecs
PLATE, FACE, FILLED = ("plate.R", "plate.G", "plate.B"), "face.A", "filled.A"
SHOT_CHANNELS = PLATE + (FACE, FILLED)  # besides R, G, B, A (the head)
FRAME_NAME = "frame.{:06d}.exr"  # 0-based frame index of the source clip
PREFIX = "exmap:"
COLOR_SPACE = "lin_rec709_scene"  # oiio:ColorSpace, written by OpenImageIO as colorInteropID
Attribute = int | float | str | tuple[float, ...]


def exr_name(frame: int) -> str:
    """File name of frame ``frame`` (0-based index in the source clip): ``frame.000012.exr``."""
    return FRAME_NAME.format(frame)


def srgb_decode(srgb: np.ndarray) -> np.ndarray:
    """sRGB-encoded values (uint8 or float in [0, 1]) -> scene-linear float32, elementwise."""
    return srgb_to_linear(to_unit_float(srgb).astype(np.float32, copy=False))


def _bits(x: np.ndarray) -> np.ndarray:
    """The bit patterns of a float array, as unsigned integers of the same size."""
    return x.view(np.dtype(f"u{x.dtype.itemsize}"))


def coverage_box(srgb: np.ndarray, alpha: np.ndarray) -> tuple[slice, slice]:
    """Rows and columns outside which ``srgb_to_linear(srgb) * alpha`` is +0 at every pixel.

    Parameters
    ----------
    srgb : (H, W, 3) uint8 or float sRGB-encoded frame.
    alpha : (H, W) float16 or float32 coverage.

    Returns
    -------
    (rows, columns) slices: the bounding box of the pixels whose alpha is not +0 (its bit pattern
    is not all zeros: -0 and NaN count as covered), or the whole frame where some colour outside
    that box is negative, -0, infinite or NaN (its product with +0 is -0 or NaN). Empty slices
    when every alpha is +0 and the frame is finite and non-negative.
    """
    import cv2

    height, width = alpha.shape
    x, y, w, h = cv2.boundingRect((_bits(alpha) != 0).view(np.uint8))
    if srgb.dtype == np.uint8:
        return slice(y, y + h), slice(x, x + w)
    # finite, sign bit clear: the bit pattern below that of +inf
    inf = _bits(np.array(np.inf, srgb.dtype))
    outside = [srgb[:y], srgb[y + h :], srgb[y : y + h, :x], srgb[y : y + h, x + w :]] if w else [srgb]
    if any(part.size and _bits(part).max() >= inf for part in outside):
        return slice(0, height), slice(0, width)
    return slice(y, y + h), slice(x, x + w)


def to_linear_rgba(srgb: np.ndarray, alpha: np.ndarray | None = None) -> np.ndarray:
    """sRGB frame and optional alpha -> premultiplied scene-linear RGBA, as the half floats stored.

    Parameters
    ----------
    srgb : (H, W, 3) float in [0, 1] (sRGB-encoded) or uint8
        Half floats (the synthesized frames) are decoded by table lookup
        (:func:`stages.writers.lut.apply_elementwise`: the same values).
    alpha : (H, W, 1) or (H, W) float in [0, 1], optional
        Coverage (the face mask). ``None`` means opaque.

    Returns
    -------
    (H, W, 4) float16: ``(R, G, B) = srgb_to_linear(srgb) * alpha`` and ``A = alpha``
    (OpenEXR associated alpha), computed in float32 and rounded once to the nearest half (ties to
    even): the values ``numpy``'s or OpenEXR's own conversion of the float32 products gives. The
    products are rounded by OpenCV as it multiplies (one vectorized pass that releases the GIL,
    where numpy's float16 conversion is a slow scalar loop), so the file writer converts nothing.
    They are computed inside :func:`coverage_box` only (the face: about half the demo's frame);
    outside it they are +0, the value of the product there. The array is a view of planar
    memory (each channel contiguous, what the EXR scanlines are made of).
    """
    import cv2

    height, width = srgb.shape[:2]
    planes = np.zeros((4, height, width), np.float16)
    alpha = np.ones((height, width), np.float16) if alpha is None else np.asarray(alpha).reshape(height, width)
    if alpha.dtype == np.float16:
        planes[3] = alpha
    else:
        alpha = np.asarray(alpha, np.float32)
        planes[3] = cv2.multiply(alpha, 1.0, dtype=cv2.CV_16F)
    rows, columns = coverage_box(srgb, alpha)
    if rows.stop > rows.start:
        coverage = cv2.multiply(np.ascontiguousarray(alpha[rows, columns]), 1.0, dtype=cv2.CV_32F)
        linear = apply_elementwise(srgb_decode, np.moveaxis(srgb[rows, columns], 2, 0))  # (3, h, w)
        for plane, channel in zip(planes[:3], linear):
            cv2.multiply(channel, coverage, dst=plane[rows, columns], dtype=cv2.CV_16F)
    return np.moveaxis(planes, 0, -1)


def _half(plane: np.ndarray) -> np.ndarray:
    """``(H, W)`` float -> float16, rounded once to the nearest (OpenCV's conversion, GIL released)."""
    import cv2

    return plane if plane.dtype == np.float16 else cv2.multiply(np.ascontiguousarray(plane, np.float32), 1.0, dtype=cv2.CV_16F)


def shot_channels(
    srgb: np.ndarray, head: np.ndarray, face: np.ndarray | None = None, filled: np.ndarray | None = None
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The channels of a shot EXR (module docstring): the head premultiplied, the plate, the mattes.

    Parameters
    ----------
    srgb : (H, W, 3) float (sRGB-encoded, in [0, 1]) or uint8: the whole frame
    head : (H, W) or (H, W, 1) float in [0, 1]: the head matte
    face, filled : (H, W) or (H, W, 1) float in [0, 1], optional: the face matte, the filled matte

    Returns
    -------
    rgba : (H, W, 4) float16: linear colour times ``head``, and ``head`` (view of planar memory)
    layers : ``{"plate.R": (H, W) float16, ..., "face.A": ..., "filled.A": ...}`` (the mattes given)
    """
    return linear_shot_channels(apply_elementwise(srgb_decode, np.moveaxis(srgb, 2, 0)), head, face, filled)


def linear_shot_channels(
    linear: np.ndarray, head: np.ndarray, face: np.ndarray | None = None, filled: np.ndarray | None = None
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """:func:`shot_channels` of a frame already in scene-linear light, ``linear (3, H, W)`` float32 (planar)."""
    import cv2

    height, width = linear.shape[1:]
    head32 = np.ascontiguousarray(np.asarray(head).reshape(height, width), np.float32)
    linear = np.ascontiguousarray(linear, np.float32)
    planes = np.empty((4, height, width), np.float16)
    for plane, channel in zip(planes[:3], linear):
        cv2.multiply(channel, head32, dst=plane, dtype=cv2.CV_16F)
    planes[3] = _half(head32)
    layers = {name: _half(channel) for name, channel in zip(PLATE, linear)}
    for name, matte in ((FACE, face), (FILLED, filled)):
        if matte is not None:
            layers[name] = _half(np.asarray(matte).reshape(height, width))
    return np.moveaxis(planes, 0, -1), layers


def frame_attributes(
    frame: int,
    *,
    fps: float,
    pose: Mapping[str, np.ndarray] | None = None,
    similarity: Mapping[str, np.ndarray] | None = None,
) -> dict[str, Attribute]:
    """The ``exmap:`` header attributes of one frame.

    Parameters
    ----------
    frame : 0-based frame index in the source clip.
    fps : frame rate of the source clip; ``exmap:time_s = frame / fps``.
    pose : one frame of a ``pose`` bundle (``rvec (3,)``, ``tvec (3,)``, ``valid ()``), optional.
    similarity : one frame of a ``similarity`` bundle (``params (4,)`` = (a, b, tx, ty) of eq. 8,
        ``valid ()``), optional.
    """
    attrs: dict[str, Attribute] = {
        PREFIX + "frame": int(frame),
        PREFIX + "time_s": float(frame / fps),
        PREFIX + "fps": float(fps),
    }
    if pose is not None:
        attrs[PREFIX + "pose_rvec"] = tuple(float(v) for v in pose["rvec"])
        attrs[PREFIX + "pose_tvec"] = tuple(float(v) for v in pose["tvec"])
        attrs[PREFIX + "pose_valid"] = int(bool(pose["valid"]))
    if similarity is not None:
        attrs[PREFIX + "similarity"] = tuple(float(v) for v in similarity["params"])
        attrs[PREFIX + "similarity_valid"] = int(bool(similarity["valid"]))
    return attrs


def head_attributes(head3d: Mapping[str, np.ndarray], frame: int) -> dict[str, Attribute]:
    """``exmap:head_R`` (9 floats, row-major) and ``exmap:head_t_mm`` (3) of one frame of a ``head3d``
    bundle: the rigid motion ``X' = R X + t`` of the target's 3D model in its camera's frame."""
    return {
        PREFIX + "head_R": tuple(float(x) for x in np.asarray(head3d["R"][frame]).ravel()),
        PREFIX + "head_t_mm": tuple(float(x) for x in np.asarray(head3d["t"][frame])),
    }


def exr_spec(width: int, height: int, *, attributes: Mapping[str, Attribute], compression: str) -> oiio.ImageSpec:
    """OpenImageIO header of a half-float RGBA EXR with the given extra attributes.

    Float tuples are written as ``float[n]`` attributes. ``DateTime`` is set empty (not written) so
    that the same frame always gives the same bytes (resumed runs match uninterrupted ones).
    """
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(width, height, 4, "half")
    spec.channelnames = ("R", "G", "B", "A")
    spec.alpha_channel = 3
    spec.attribute("compression", compression)
    spec.attribute("oiio:ColorSpace", COLOR_SPACE)
    spec.attribute("DateTime", "")
    for key, value in attributes.items():
        if isinstance(value, tuple):
            spec.attribute(key, oiio.TypeDesc(f"float[{len(value)}]"), value)
        else:
            spec.attribute(key, value)
    return spec


def oiio_write_exr(
    path: Path,
    pixels: np.ndarray,
    *,
    attributes: Mapping[str, Attribute],
    compression: str,
    names: tuple[str, ...] | None = None,
    floats: tuple[str, ...] = ("Z",),
) -> None:
    """Write ``pixels`` ``(H, W, 4)`` (RGBA, half) or ``(H, W, 5)`` (RGBA half + float Z), any strides, with
    OpenImageIO, in place (not atomic): the codecs ``piz`` and ``rle``, and the reference the
    tests and the benchmark compare :func:`write_exr` with. With ``names``, ``pixels`` ``(H, W, C)``
    holds those channels (RGBA first), the ones named in ``floats`` stored as 32-bit floats, the
    others as half.

    Raises
    ------
    OSError
        OpenImageIO cannot open or write the file (its message).
    """
    import OpenImageIO as oiio

    height, width, channels = pixels.shape
    spec = exr_spec(width, height, attributes=attributes, compression=compression)
    if names is None and channels == 5:
        names = ("R", "G", "B", "A", "Z")
    if names is not None:
        spec.nchannels = len(names)
        spec.channelnames = tuple(names)
        spec.channelformats = tuple(oiio.FLOAT if n in floats else oiio.HALF for n in names)
    out = oiio.ImageOutput.create("openexr")
    if out is None or not out.open(str(path), spec):
        reason = out.geterror() if out is not None else oiio.geterror()
        raise OSError(reason or "open failed")
    ok = out.write_image(np.ascontiguousarray(pixels))  # OpenImageIO takes interleaved channels only
    ok = out.close() and ok
    if not ok:
        raise OSError(out.geterror() or "write failed")


DEPTH_UNIT = "mm"


def write_exr(
    path: Path,
    rgba: np.ndarray,
    *,
    attributes: Mapping[str, Attribute],
    compression: str = "zip",
    zip_level: int = ZIP_LEVEL,
    depth: np.ndarray | None = None,
    layers: Mapping[str, np.ndarray] | None = None,
) -> None:
    """Write one half-float RGBA EXR atomically (temp name in the same folder, then rename).

    ``none``, ``zips`` and ``zip`` are written by :mod:`stages.writers.exr_file` (numpy and
    zlib-ng's deflate), ``piz`` and ``rle`` by OpenImageIO (:func:`oiio_write_exr`); both give the
    same header attributes with the same EXR types and the same half floats.

    Parameters
    ----------
    path : final file name (``.exr``).
    rgba : (H, W, 4) float16 (written as it is) or another float type (rounded to float32, then
        to the nearest half, ties to even, as OpenEXR's conversion does), premultiplied
        scene-linear RGBA (see :func:`to_linear_rgba`).
    attributes : extra header attributes (see :func:`frame_attributes`).
    compression : one of ``COMPRESSIONS`` (all lossless).
    zip_level : zlib deflate level (``ZIP_LEVELS``: 1 fastest .. 9 smallest) of ``zip`` / ``zips``
        (other codecs ignore it).
    depth : optional (H, W) camera depth of the surface at each pixel centre, in ``DEPTH_UNIT``
        (mm, z away from the camera; ``inf`` where no surface is): written as a 32-bit float ``Z``
        channel after RGBA, with the header attribute ``exmap:depth_unit``.
    layers : optional further channels, name -> (H, W) float16 (layer-prefixed names such as
        ``plate.R``, ``face.A``: :data:`SHOT_CHANNELS`).

    Raises
    ------
    ValueError
        ``rgba`` is not (H, W, 4), ``depth`` is not (H, W), ``compression`` or ``zip_level`` unknown.
    StageError
        The file cannot be created or written (folder missing or read-only, disk full).
    """
    if rgba.ndim != 3 or rgba.shape[2] != 4:
        raise ValueError(f"expected rgba (H, W, 4), got {rgba.shape}")
    if compression not in COMPRESSIONS:
        raise ValueError(f"expected compression in {COMPRESSIONS}, got {compression!r}")
    height, width = rgba.shape[:2]
    with np.errstate(over="ignore"):  # beyond the half range: inf, as OpenEXR converts
        pixels = rgba if rgba.dtype == np.float16 else np.asarray(rgba, np.float32).astype(np.float16)
    if depth is not None:
        if depth.shape != (height, width):
            raise ValueError(f"expected depth ({height}, {width}), got {depth.shape}")
        attributes = {**attributes, PREFIX + "depth_unit": DEPTH_UNIT}
    channels = {name: pixels[..., c] for c, name in enumerate("RGBA")}
    if depth is not None:
        channels["Z"] = np.asarray(depth, np.float32)
    for name, plane in (layers or {}).items():
        if plane.shape != (height, width) or plane.dtype != np.float16:
            raise ValueError(f"expected layer {name!r} ({height}, {width}) float16, got {plane.shape} {plane.dtype}")
        channels[name] = plane
    try:
        with atomic_write(path) as tmp:
            if compression in COMPRESSION_CODES:
                with open(tmp, "wb") as file:
                    write_scanline_exr(
                        file,
                        channels,
                        attributes={"colorInteropID": COLOR_SPACE, **attributes},
                        compression=compression,
                        level=zip_level,
                    )
            elif len(channels) == 4:
                oiio_write_exr(tmp, pixels, attributes=attributes, compression=compression)
            else:
                stacked = np.stack([np.asarray(c, np.float32) for c in channels.values()], axis=2)
                oiio_write_exr(tmp, stacked, attributes=attributes, compression=compression, names=tuple(channels))
    except OSError as err:
        raise StageError(f"cannot write EXR {path}: {err.strerror or err}") from err


class WriteExr(FrameStage):
    """Writes ``frame.%06d.exr`` per frame: half float, scene-linear, premultiplied RGBA, metadata."""

    name = "write.exr"
    version = "5"
    doc = "EXR per frame: half float, scene-linear (sRGB decoded); the head (associated alpha), the plate, face and filled mattes"
    inputs = {
        "frames": "frames",
        "mask": "frames",
        "head_matte": "frames",
        "filled": "frames",
        "pose": HEAD_POSES,
        "similarity": SIMILARITY,
        "head": HEAD3D,
    }
    optional_inputs = frozenset({"mask", "head_matte", "filled", "pose", "similarity", "head"})
    outputs = {"exr": "files"}
    params = (
        Param("compression", str, "zip", "lossless EXR compression", choices=COMPRESSIONS),
        Param(
            "zip_level",
            int,
            ZIP_LEVEL,
            "deflate level of zip/zips (zlib: 1 fastest, 9 smallest)",
            min=ZIP_LEVELS.start,
            max=ZIP_LEVELS.stop - 1,
        ),
        Param("threads", int, 0, "frames written in parallel; 0 = one per CPU core", in_key=False, min=0, max=256),
        Param(
            "layers",
            str,
            "shot",
            "shot: with 'head_matte', the head, the plate and the mattes; face: RGBA with alpha = "
            "the face mask only (RGB 0 outside the face: about 40 % of the shot's CPU per frame)",
            choices=("shot", "face"),
        ),
    )

    def process(
        self, start: int, stop: int, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context
    ) -> dict[str, Any]:
        stream = inputs["frames"]
        info = stream.info
        frames = stream.read(start, stop)
        if frames.ndim != 4 or frames.shape[3] != 3:
            raise StageError(f"write.exr: input 'frames' must be RGB (B, H, W, 3), got {frames.shape}")
        mattes = {}
        for port in ("mask", "head_matte", "filled"):
            if inputs.get(port) is None:
                continue
            mattes[port] = inputs[port].read(start, stop)
            if inputs[port].info.frames != info.frames or mattes[port].shape[1:] != frames.shape[1:3] + (1,):
                raise StageError(
                    f"write.exr: input '{port}' ({inputs[port].info.frames} frames of shape {mattes[port].shape[1:]}) "
                    f"does not match 'frames' ({info.frames} of shape {frames.shape[1:3] + (1,)})"
                )
        masks = mattes.get("mask")
        head3d = inputs.get("head")
        if head3d is not None and len(head3d["R"]) != info.frames:
            raise StageError(f"write.exr: input 'head' has {len(head3d['R'])} frames, 'frames' {info.frames}")
        pose, similarity = inputs.get("pose"), inputs.get("similarity")
        for port, bundle in (("pose", pose), ("similarity", similarity)):
            if bundle is not None:
                check_bundle(bundle, stage=self.name, port=port, kind=port, frames=info.frames)
        folder = ctx.files_dir("exr")
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise StageError(f"write.exr: cannot create output folder {folder}: {err.strerror or err}") from err

        def write_one(i: int) -> None:
            frame = start + i
            attributes = frame_attributes(
                frame,
                fps=info.fps,
                pose=None if pose is None else {k: pose[k][frame] for k in ("rvec", "tvec", "valid")},
                similarity=None if similarity is None else {k: similarity[k][frame] for k in ("params", "valid")},
            )
            if head3d is not None:
                attributes.update(head_attributes(head3d, frame))
            layers = None
            if "head_matte" in mattes and params.get("layers", "shot") == "shot":
                rgba, layers = shot_channels(
                    frames[i],
                    mattes["head_matte"][i],
                    None if masks is None else masks[i],
                    mattes["filled"][i] if "filled" in mattes else None,
                )
            else:
                rgba = to_linear_rgba(frames[i], None if masks is None else masks[i])
            write_exr(
                folder / exr_name(frame),
                rgba,
                attributes=attributes,
                compression=params["compression"],
                zip_level=params["zip_level"],
                layers=layers,
            )

        workers = min(params["threads"] or os.cpu_count() or 1, len(frames))
        with ThreadPoolExecutor(max_workers=max(workers, 1), thread_name_prefix="write.exr") as pool:
            list(pool.map(write_one, range(len(frames))))
        return {"exr": None}
