"""EXR frames of the 3D render: half-float premultiplied scene-linear RGBA plus a float ``Z`` channel.

The header is ``write.exr``'s (:func:`stages.writers.exr.exr_spec`: colour space, compression,
``exmap:`` attributes) with one more channel: ``Z``, 32-bit float, the camera depth of the
rendered surface at each pixel centre in millimetres (the target camera's frame, z away from the
camera; ``inf`` where no surface is), and the attribute ``exmap:depth_unit = "mm"``.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from runner.stage import StageError
from stages.writers.atomic import atomic_write
from stages.writers.exr import Attribute, exr_spec

__all__ = ["DEPTH_UNIT", "write_exr_depth"]

DEPTH_UNIT = "mm"


def write_exr_depth(path: Path, rgba: np.ndarray, depth: np.ndarray, *, attributes: Mapping[str, Attribute], compression: str = "zip") -> None:
    """Write one RGBA + Z EXR atomically.

    Parameters
    ----------
    path : final file name (``.exr``)
    rgba : (H, W, 4) float, premultiplied scene-linear RGBA (stored as half)
    depth : (H, W) float, camera depth in mm, ``inf`` where empty (stored as float)
    attributes : extra header attributes (:func:`stages.writers.exr.frame_attributes`)

    Raises
    ------
    ValueError
        Shapes disagree.
    StageError
        The file cannot be written.
    """
    import OpenImageIO as oiio

    rgba = np.asarray(rgba, np.float32)
    depth = np.asarray(depth, np.float32)
    if rgba.ndim != 3 or rgba.shape[2] != 4 or depth.shape != rgba.shape[:2]:
        raise ValueError(f"expected rgba (H, W, 4) and depth (H, W), got {rgba.shape} and {depth.shape}")
    H, W = depth.shape
    spec = exr_spec(W, H, attributes={**attributes, "exmap:depth_unit": DEPTH_UNIT}, compression=compression)
    spec.nchannels = 5
    spec.channelnames = ("R", "G", "B", "A", "Z")
    spec.channelformats = (oiio.HALF,) * 4 + (oiio.FLOAT,)
    pixels = np.ascontiguousarray(np.concatenate([rgba, depth[..., None]], axis=2))
    try:
        with atomic_write(path) as tmp:
            out = oiio.ImageOutput.create("openexr")
            if out is None or not out.open(str(tmp), spec):
                reason = out.geterror() if out is not None else oiio.geterror()
                raise StageError(f"cannot write EXR {path}: {reason or 'open failed'}")
            ok = out.write_image(pixels)
            ok = out.close() and ok
            if not ok:
                raise StageError(f"cannot write EXR {path}: {out.geterror() or 'write failed'}")
    except OSError as err:
        raise StageError(f"cannot write EXR {path}: {err.strerror or err}") from err
