"""Which columns of a points bundle are the layout's rigid points (paper Sec. 12.1: the hairline
points and the two inner eye corners), found by name."""

from __future__ import annotations

from typing import Any

import numpy as np

from runner.stage import StageError


def named_columns(names: np.ndarray, wanted: tuple[str, ...]) -> np.ndarray:
    """Indices ``(K,)`` into ``names`` of the ``wanted`` names that are present, in ``wanted`` order."""
    position = {str(n): i for i, n in enumerate(names)}
    return np.array([position[w] for w in wanted if w in position], dtype=np.int64)


def param_columns(names: np.ndarray, wanted: list[str], *, stage: str, param: str) -> np.ndarray:
    """Columns ``(K,)`` into the bundle's point ``names`` of the names parameter ``param`` gives,
    in its order; a :class:`StageError` naming ``stage``, ``param`` and every name that is not
    among the points."""
    present = set(map(str, names))
    missing = [n for n in wanted if n not in present]
    if missing:
        raise StageError(f"{stage}: parameter {param} names {missing} that are not tracked points of the layout")
    return named_columns(names, tuple(wanted))


def rigid_columns(names: np.ndarray, layout: Any, *, at_least: int, stage: str) -> np.ndarray:
    """Columns ``(R,)`` of the layout's rigid points among the bundle's point ``names``; a
    :class:`StageError` naming ``stage`` when fewer than ``at_least`` are there."""
    wanted = tuple(layout.point_names[i] for i in layout.rigid)
    columns = named_columns(names, wanted)
    if len(columns) < at_least:
        raise StageError(
            f"{stage}: the points carry {len(columns)} of the layout's rigid points {list(wanted)}; "
            f"at least {at_least} are needed"
        )
    return columns
