"""Validation of the editor's request bodies (decoded JSON) into arrays.

Every function raises ``ValueError`` saying which field was wrong, what was expected and what
was got; the server answers it with a 400 JSON error. Positions are px in the target
neutral's frame and must lie within ``limit`` px of the origin (a few image sizes: anything
farther is not an expression).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

MAX_KEYFRAMES = 1000
MAX_FPS = 240.0
MAX_SECONDS = 600.0  # longest exported performance
MAX_EXPORT_FRAMES = 36_000  # frames of one export (10 min at 60 fps; 77 MB of 134 points)


def _field(body: Any, name: str) -> Any:
    if not isinstance(body, dict):
        raise ValueError(f"expected a JSON object, got {type(body).__name__}")
    if name not in body:
        raise ValueError(f"field '{name}' is missing")
    return body[name]


def _number(value: Any, where: str, *, low: float, high: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not _finite(value):
        raise ValueError(f"{where}: expected a finite number, got {value!r:.40}")
    if not low <= value <= high:
        raise ValueError(f"{where}: expected a number in [{low:g}, {high:g}], got {value!r}")
    return float(value)


def _finite(value: int | float) -> bool:
    """Whether ``value`` is a finite number a float can hold (JSON integers have any length)."""
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def _integer(value: Any, where: str, *, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{where}: expected an integer, got {value!r}")
    if not low <= value <= high:
        raise ValueError(f"{where}: expected an integer in {low}..{high}, got {value}")
    return value


def geometry(value: Any, where: str, *, n_points: int, limit: float) -> np.ndarray:
    """A ``(n_points, 2)`` list of finite positions within ``limit`` px -> float64 array."""
    if not isinstance(value, list) or len(value) != n_points:
        got = f"{len(value)} entries" if isinstance(value, list) else type(value).__name__
        raise ValueError(f"{where}: expected a list of {n_points} [x, y] pairs, got {got}")
    out = np.empty((n_points, 2))
    for k, pair in enumerate(value):
        if not isinstance(pair, list) or len(pair) != 2:
            raise ValueError(f"{where}[{k}]: expected [x, y], got {pair!r}")
        out[k] = [_number(v, f"{where}[{k}]", low=-limit, high=limit) for v in pair]
    return out


def sequence_number(body: Any) -> tuple[str, int]:
    """``client`` (a short id string) and ``seq`` (a non-negative integer) of an image request."""
    client = _field(body, "client")
    if not isinstance(client, str) or not 1 <= len(client) <= 64:
        raise ValueError(f"field 'client': expected a string of 1-64 characters, got {client!r}")
    return client, _integer(_field(body, "seq"), "field 'seq'", low=0, high=2**53)


def flag(body: Any, name: str) -> bool:
    """An optional boolean field (absent: False)."""
    if not isinstance(body, dict):
        raise ValueError(f"expected a JSON object, got {type(body).__name__}")
    value = body.get(name, False)
    if not isinstance(value, bool):
        raise ValueError(f"field '{name}': expected true or false, got {value!r:.40}")
    return value


def render_request(body: Any, *, n_points: int, limit: float) -> tuple[np.ndarray | None, dict[int, np.ndarray]]:
    """``{"base": null | [[x, y] * N], "pinned": [[index, x, y], ...]}`` -> (base, pinned).

    Indices must be distinct and in ``0..n_points - 1``.
    """
    base_value = _field(body, "base")
    base = None if base_value is None else geometry(base_value, "field 'base'", n_points=n_points, limit=limit)
    entries = _field(body, "pinned")
    if not isinstance(entries, list) or len(entries) > n_points:
        raise ValueError(f"field 'pinned': expected a list of at most {n_points} [index, x, y], got {entries!r:.80}")
    pinned: dict[int, np.ndarray] = {}
    for k, entry in enumerate(entries):
        where = f"field 'pinned'[{k}]"
        if not isinstance(entry, list) or len(entry) != 3:
            raise ValueError(f"{where}: expected [index, x, y], got {entry!r}")
        index = _integer(entry[0], f"{where} index", low=0, high=n_points - 1)
        if index in pinned:
            raise ValueError(f"{where}: point {index} is pinned twice")
        pinned[index] = np.array([_number(v, where, low=-limit, high=limit) for v in entry[1:]])
    return base, pinned


def inbetween_request(body: Any, *, n_points: int, limit: float) -> tuple[np.ndarray, np.ndarray]:
    """``{"from": [[x, y] * N], "to": [[x, y] * N]}`` -> the two geometries."""
    return tuple(geometry(_field(body, key), f"field '{key}'", n_points=n_points, limit=limit) for key in ("from", "to"))


def export_request(body: Any, *, n_points: int, limit: float) -> tuple[np.ndarray, np.ndarray, float]:
    """``{"fps": F, "keyframes": [{"time_s": t, "points": [[x, y] * N]}, ...]}``
    -> (times (K,), geometries (K, N, 2), fps); times increase strictly from >= 0, and span at
    most :data:`MAX_EXPORT_FRAMES` frames at ``fps``."""
    fps = _number(_field(body, "fps"), "field 'fps'", low=1e-3, high=MAX_FPS)
    keys = _field(body, "keyframes")
    if not isinstance(keys, list) or not 1 <= len(keys) <= MAX_KEYFRAMES:
        raise ValueError(f"field 'keyframes': expected a list of 1..{MAX_KEYFRAMES} keyframes, got {keys!r:.80}")
    times = np.array(
        [_number(_field(k, "time_s"), f"keyframes[{i}].time_s", low=0.0, high=MAX_SECONDS) for i, k in enumerate(keys)]
    )
    if (np.diff(times) <= 0).any():
        raise ValueError(f"field 'keyframes': times must increase strictly, got {times.tolist()}")
    frames = math.floor((times[-1] - times[0]) * fps) + 1
    if frames > MAX_EXPORT_FRAMES:
        raise ValueError(
            f"the export would have {frames} frames ({times[-1] - times[0]:g} s at {fps:g} fps), at most "
            f"{MAX_EXPORT_FRAMES}: lower fps or export a shorter span"
        )
    geoms = np.stack(
        [geometry(_field(k, "points"), f"keyframes[{i}].points", n_points=n_points, limit=limit) for i, k in enumerate(keys)]
    )
    return times, geoms, fps
