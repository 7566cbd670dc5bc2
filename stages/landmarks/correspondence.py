"""A layout's feature points as fixed combinations of face-mesh vertices (data, not code).

A correspondence file (YAML, e.g. ``stages/layouts/zhang134_mediapipe.yaml``) gives, for every
point of a layout, either one mesh vertex index or a weighted combination of vertices::

    name: zhang134_mediapipe
    layout: zhang134          # the layout whose points are listed
    mesh_vertices: 478        # MediaPipe's face mesh with irises
    points:
      eye_l_0: 133                                   # one vertex
      brow_l_1: {vertices: [52, 53], weights: [0.5, 0.5]}
      hairline_2: {vertices: [10, 151], weights: [1.5, -0.5], note: extrapolated above the mesh}

Weights sum to 1, so the point is an affine combination of vertices (it moves with the mesh and
is unchanged by a translation of the image); negative weights extrapolate. The point of layout
row ``n`` in frame ``t`` is ``p[t, n] = sum_m W[n, m] v[t, m]`` (:func:`layout_from_mesh`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from stages.layout import LAYOUT_DIR, Layout, load_layout, read_yaml

WEIGHT_SUM_TOLERANCE = 1e-6


@dataclass(frozen=True)
class Correspondence:
    """A validated correspondence: ``weights (N, M)`` float64, row ``n`` for layout point
    ``point_names[n]`` over the ``M`` mesh vertices; each row sums to 1."""

    name: str
    point_names: tuple[str, ...]
    weights: np.ndarray

    @property
    def n_vertices(self) -> int:
        """M, the mesh vertex count the correspondence is written for."""
        return self.weights.shape[1]


def layout_from_mesh(xy: np.ndarray, correspondence: Correspondence) -> np.ndarray:
    """The layout's feature points from the face mesh of every frame.

    Parameters
    ----------
    xy
        ``(T, M, D)`` mesh vertex positions (px; D = 2 for x, y, or 1 for the depth z, or 3);
        NaN rows stay NaN.
    correspondence
        The layout-to-mesh correspondence (``weights (N, M)``).

    Returns
    -------
    numpy.ndarray
        ``(T, N, D)`` float64, ``p[t, n] = sum_m weights[n, m] xy[t, m]``.
    """
    xy = np.asarray(xy, dtype=np.float64)
    m = correspondence.n_vertices
    if xy.ndim != 3 or xy.shape[1] != m:
        raise ValueError(f"expected mesh points of shape (T, {m}, D), got {xy.shape}")
    used = np.flatnonzero(correspondence.weights.any(axis=0))
    # only the vertices in use: a NaN elsewhere (0 * NaN) must not reach the points
    return np.einsum("nm,tmd->tnd", correspondence.weights[:, used], xy[:, used])


def load_correspondence(name_or_path: str | Path, *, layout: Layout | None = None) -> Correspondence:
    """Load and validate a correspondence file.

    Parameters
    ----------
    name_or_path
        A YAML path, or the name of a bundled file in ``stages/layouts/`` (``"zhang134_mediapipe"``).
    layout
        The layout whose points the file must list (each exactly once); by default the layout
        named in the file's ``layout`` field.

    Raises
    ------
    ValueError
        A field or point entry is wrong: unknown or missing point names, vertex indices out of
        range, weights not summing to 1, lists of different lengths; the message names the
        file and the entry.
    runner.stage.StageError
        The file cannot be read or is not YAML.
    """
    path = Path(name_or_path)
    if not path.suffix and not path.exists():
        path = LAYOUT_DIR / f"{name_or_path}.yaml"
    return parse_correspondence(read_yaml(path, what="correspondence"), layout=layout, source=str(path))


def parse_correspondence(data: Any, *, layout: Layout | None = None, source: str = "<correspondence>") -> Correspondence:
    """Validate the mapping read from a correspondence file (see the module docstring) and build
    the :class:`Correspondence`; ``source`` names the file in error messages."""

    def fail(field: str, msg: str) -> ValueError:
        return ValueError(f"correspondence {source}: field '{field}': {msg}")

    if not isinstance(data, dict):
        raise ValueError(f"correspondence {source}: expected a mapping at the top level")
    for key in ("name", "layout", "mesh_vertices", "points"):
        if key not in data:
            raise fail(key, "missing")
    m = data["mesh_vertices"]
    if not isinstance(m, int) or isinstance(m, bool) or m < 1:
        raise fail("mesh_vertices", f"expected a positive integer, got {m!r}")
    if layout is None:
        layout = load_layout(data["layout"])
    points = data["points"]
    if not isinstance(points, dict):
        raise fail("points", "expected a mapping of point name -> vertex or {vertices, weights}")
    unknown = [k for k in points if k not in layout.point_names]
    if unknown:
        raise fail(f"points.{unknown[0]}", f"unknown point name for layout {layout.name!r}")
    missing = [k for k in layout.point_names if k not in points]
    if missing:
        raise fail("points", f"no entry for layout point {missing[0]!r} ({len(missing)} missing)")

    weights = np.zeros((layout.n_points, m))
    for row, name in enumerate(layout.point_names):
        entry = points[name]
        field = f"points.{name}"
        if isinstance(entry, dict):
            extra = set(entry) - {"vertices", "weights", "note"}
            if extra:
                raise fail(field, f"unknown key {sorted(extra)[0]!r} (expected vertices, weights, note)")
            vertices, w = entry.get("vertices"), entry.get("weights")
        else:
            vertices, w = [entry], [1.0]
        if (
            not isinstance(vertices, list)
            or not vertices
            or not all(isinstance(v, int) and not isinstance(v, bool) for v in vertices)
        ):
            raise fail(field, f"expected a vertex index or a non-empty list of them, got {vertices!r}")
        bad = [v for v in vertices if not 0 <= v < m]
        if bad:
            raise fail(field, f"vertex index {bad[0]} out of range [0, {m})")
        if len(set(vertices)) != len(vertices):
            raise fail(field, "a vertex is listed twice")
        if (
            not isinstance(w, list)
            or len(w) != len(vertices)
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x) for x in w)
        ):
            raise fail(field, f"expected {len(vertices)} finite weights, got {w!r}")
        if abs(sum(w) - 1.0) > WEIGHT_SUM_TOLERANCE:
            raise fail(field, f"weights sum to {sum(w):.6g}, expected 1")
        weights[row, vertices] = w
    return Correspondence(name=str(data["name"]), point_names=layout.point_names, weights=weights)
