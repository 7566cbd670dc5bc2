"""The points file the editor exports and ``points.load``, the stage that feeds it to the pipeline.

A points file is an ``.npz`` (no pickle) with ``xy (T, N, 2) f8`` px (x right, y down, origin
at the centre of the top-left pixel, the target neutral's frame), ``names (N,) str`` (the
layout's point names) and ``fps ()`` frames/s: a performance made of keyframes, rendered by
``editor/render_keyframes.yaml`` like the geometry of a tracked clip.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from runner.stage import Context, SequenceStage, StageError
from stages.geometry.bundles import POINTS
from stages.npz_file import NpzError, read_npz

MAX_POINT_VALUES = 100_000_000  # values of one array (800 MB as float64: ~1.7 h of 134 points at 60 fps)


def points_file_bytes(xy: np.ndarray, names: tuple[str, ...] | np.ndarray, *, fps: float) -> bytes:
    """The ``.npz`` bytes of a points file.

    Parameters
    ----------
    xy : (T, N, 2) float, px, finite
    names : (N,) str
    fps : float, frames/s, > 0

    Raises
    ------
    ValueError
        Shapes disagree or values are not finite.
    """
    xy = np.asarray(xy, np.float64)
    names = np.asarray(names, dtype=str)
    if xy.ndim != 3 or xy.shape[2] != 2 or len(xy) == 0 or names.shape != (xy.shape[1],):
        raise ValueError(f"expected xy (T, N, 2) with T >= 1 and names (N,), got {xy.shape} and {names.shape}")
    if not np.isfinite(xy).all():
        raise ValueError("xy must be finite")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a finite number > 0, got {fps!r}")
    buffer = io.BytesIO()
    np.savez(buffer, xy=xy, names=names, fps=np.float64(fps))
    return buffer.getvalue()


def read_points_file(path: Path) -> dict[str, np.ndarray]:
    """A points file as a ``points`` bundle: ``xy``, ``valid (T, N)`` all True, ``names``, ``fps``.

    Raises
    ------
    StageError
        The file cannot be read as an npz without pickle, or a field is missing or malformed
        (the message names the file and the field).
    """
    try:
        fields = read_npz(path, ("xy", "names", "fps"), max_values=MAX_POINT_VALUES)
    except NpzError as exc:
        raise StageError(f"not a points file: {exc}") from None
    for key in ("xy", "names", "fps"):
        if key not in fields:
            raise StageError(f"{path}: field '{key}' is missing")
    xy, names, fps = fields["xy"], fields["names"], fields["fps"]
    if xy.ndim != 3 or xy.shape[2] != 2 or len(xy) == 0 or not np.issubdtype(xy.dtype, np.number):
        raise StageError(f"{path}: field 'xy' must be (T, N, 2) numbers with T >= 1, got {xy.shape} {xy.dtype}")
    if not np.isfinite(xy).all():
        raise StageError(f"{path}: field 'xy' has non-finite values")
    if names.shape != (xy.shape[1],) or names.dtype.kind != "U":
        raise StageError(f"{path}: field 'names' must be ({xy.shape[1]},) strings, got {names.shape} {names.dtype}")
    if fps.shape != () or not np.issubdtype(fps.dtype, np.number) or not (np.isfinite(fps) and fps > 0):
        raise StageError(f"{path}: field 'fps' must be one number > 0, got {fps!r}")
    return {
        "xy": xy.astype(np.float64),
        "valid": np.ones(xy.shape[:2], bool),
        "names": names,
        "fps": np.asarray(fps, np.float64),
    }


class LoadPoints(SequenceStage):
    """``points.load``: a points file (the editor's keyframe export) as a ``points`` bundle."""

    name = "points.load"
    version = "1"
    doc = "read a points file (npz: xy (T,N,2) px, names (N,), fps) into a points bundle"
    inputs = {"file": "file"}
    outputs = {"points": POINTS}

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        bundle = read_points_file(Path(inputs["file"]))
        ctx.progress(len(bundle["xy"]))
        return {"points": bundle}
