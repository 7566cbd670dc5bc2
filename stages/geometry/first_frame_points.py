"""The first-frame points file of ``track.correlation`` (a ``name,x,y`` CSV or JSON): reading it
and checking it against the layout's tracked subset and the clip's frame size."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from runner.stage import StageError
from stages.geometry.correlation import inside


def read_first_frame_points(path: Path) -> tuple[list[str], np.ndarray, tuple[int, int] | None]:
    """Read named first-frame positions from a ``.csv`` (header ``name,x,y``) or ``.json`` file
    (``{"names": [...], "xy": [[x, y], ...]}`` or ``{name: [x, y], ...}``, optionally under a
    ``"points"`` key). Returns the names, an ``(N, 2)`` float64 array in px and the size
    ``(W, H)`` of the frame the points were marked on, when the file states it (a CSV comment line
    ``# frame_size: W H`` before the header, or a JSON key ``"frame_size": [W, H]``), else None."""
    path = Path(path)
    if not path.is_file():
        raise StageError(f"first-frame points file not found: {path}")
    frame_size = None
    try:
        if path.suffix.lower() == ".csv":
            lines = path.read_text().splitlines()
            for line in lines:
                key, _, value = line.lstrip("# ").partition(":")
                if line.startswith("#") and key.strip() == "frame_size":
                    frame_size = tuple(int(v) for v in value.split())
            rows = list(csv.DictReader(line for line in lines if not line.startswith("#")))
            names = [row["name"] for row in rows]
            xy = np.array([[float(row["x"]), float(row["y"])] for row in rows], dtype=np.float64)
        elif path.suffix.lower() == ".json":
            data = json.loads(path.read_text())
            if isinstance(data, dict) and "frame_size" in data:
                frame_size = tuple(int(v) for v in data["frame_size"])
            data = data.get("points", data) if isinstance(data, dict) else data
            if isinstance(data, dict) and "names" in data:
                names, xy = list(data["names"]), np.asarray(data["xy"], dtype=np.float64)
            else:
                names, xy = list(data), np.asarray(list(data.values()), dtype=np.float64)
        else:
            raise StageError(f"{path}: first-frame points must be a .csv or .json file")
    except (KeyError, ValueError, TypeError, AttributeError, json.JSONDecodeError) as exc:
        raise StageError(f"{path}: cannot read first-frame points (expected name,x,y): {exc}") from None
    if xy.ndim != 2 or xy.shape != (len(names), 2) or not np.isfinite(xy).all():
        raise StageError(f"{path}: expected one finite (x, y) pair per named point, got shape {xy.shape}")
    if frame_size is not None and len(frame_size) != 2:
        raise StageError(f"{path}: frame_size must be two integers W H, got {frame_size}")
    return [str(n) for n in names], xy, frame_size


def order_by_layout(
    path: Path,
    names: list[str],
    xy: np.ndarray,
    expected: tuple[str, ...],
    size: tuple[int, int],
    frame_size: tuple[int, int] | None = None,
) -> np.ndarray:
    """Check first-frame points against the layout's tracked subset and the clip's frame size
    ``size = (W, H)`` (and ``frame_size``, the size the file says they were marked on); return
    them ``(N, 2)`` in the layout's order."""
    if frame_size is not None and tuple(frame_size) != tuple(size):
        raise StageError(
            f"{path}: the points were marked on a {frame_size[0]}x{frame_size[1]} frame, "
            f"the clip's frames are {size[0]}x{size[1]}"
        )
    if len(set(names)) != len(names):
        raise StageError(f"{path}: duplicate point names")
    missing = [n for n in expected if n not in names]
    extra = [n for n in names if n not in expected]
    if missing or extra:
        raise StageError(
            f"{path}: {len(names)} points do not match the layout's {len(expected)} tracked points"
            f" (missing {missing[:5]}, unknown {extra[:5]})"
        )
    ordered = xy[[names.index(n) for n in expected]]
    outside = ~inside(ordered, *size)
    if outside.any():
        bad = [expected[i] for i in np.flatnonzero(outside)]
        raise StageError(f"{path}: points outside the {size[0]}x{size[1]} frame: {bad[:5]}")
    return ordered
