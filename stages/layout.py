"""The feature-point layout: named points, subregions, blending, feature point sets (data, not code).

A layout file (YAML, see ``stages/layouts/zhang134.yaml``) names the N feature points of Zhang et
al. 2006 Fig. 2a, the face subregions of Sec. 5.3 (polygons over points, plus the teeth subregion
of Sec. 8), the subregion pairs that are not blended (Sec. 7), the 1 + 4 + 16 feature point sets
of the hierarchical PCA (Sec. 10), the rigid points used for motion compensation and head pose
(Sec. 12, 12.1) and the subset a tracker follows. Files refer to points by name; the loaded
:class:`Layout` holds point indices (the row order of every ``(N, 2)`` points array).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from runner import safe_yaml
from runner.depends import depends_on
from runner.stage import StageError

LAYOUT_DIR = Path(__file__).resolve().parent / "layouts"


@dataclass(frozen=True)
class Subregion:
    """One face subregion R (Sec. 5.3).

    ``polygon`` is the closed outline as point indices in order (used to rasterize masks);
    ``points`` are the indices of feature points strictly inside it. G^R of Sec. 6 is the
    positions of ``polygon + points``. ``teeth`` marks the teeth subregion (Sec. 8).
    """

    name: str
    polygon: tuple[int, ...]
    points: tuple[int, ...]
    teeth: bool = False

    @property
    def all_points(self) -> tuple[int, ...]:
        """Indices of the feature points within or on the boundary of R (G^R of Sec. 6), sorted."""
        return tuple(sorted(set(self.polygon) | set(self.points)))


@dataclass(frozen=True)
class FeaturePointSet:
    """One feature point set of the motion-propagation hierarchy (Sec. 10), level 0, 1 or 2."""

    name: str
    level: int
    points: tuple[int, ...]


@dataclass(frozen=True)
class Layout:
    """A validated feature-point layout; see the module docstring and ``docs/fixtures.md``."""

    name: str
    point_names: tuple[str, ...]
    subregions: tuple[Subregion, ...]
    no_blend: tuple[tuple[str, str], ...]
    feature_point_sets: tuple[FeaturePointSet, ...]
    rigid: tuple[int, ...]
    tracked: tuple[int, ...]

    def index(self, name: str) -> int:
        """Row index of the feature point called ``name``; ``KeyError`` if there is none."""
        try:
            return self.point_names.index(name)
        except ValueError:
            raise KeyError(f"layout {self.name!r} has no point {name!r}") from None

    def indices(self, names: list[str] | tuple[str, ...]) -> tuple[int, ...]:
        """Row indices of several named points, in the given order."""
        return tuple(self.index(n) for n in names)

    @property
    def n_points(self) -> int:
        """N, the number of feature points."""
        return len(self.point_names)

    def subregion(self, name: str) -> Subregion:
        """The subregion called ``name``; ``KeyError`` if there is none."""
        for s in self.subregions:
            if s.name == name:
                return s
        raise KeyError(f"layout {self.name!r} has no subregion {name!r}")

    @property
    def teeth_subregion(self) -> Subregion | None:
        """The teeth subregion (Sec. 8), or None if the layout has none."""
        return next((s for s in self.subregions if s.teeth), None)


def load_layout(path_or_name: str | Path) -> Layout:
    """Load and validate a layout file.

    Parameters
    ----------
    path_or_name
        A path to a YAML layout file, or the name of a bundled layout (``"zhang134"``, the
        default of the paper: 134 points, 14 subregions + teeth, 1 + 4 + 16 feature point sets).

    Raises
    ------
    StageError
        The file is missing or unreadable, or a field is wrong; the message names the file and
        the field.
    """
    path = Path(path_or_name)
    if not path.suffix and not path.exists():
        path = LAYOUT_DIR / f"{path_or_name}.yaml"
    return parse_layout(read_yaml(path, what="layout"), source=str(path))


def read_yaml(path: Path, *, what: str, noun: str = "file", error: type[StageError] = StageError) -> Any:
    """The value of a YAML file read with :func:`runner.safe_yaml.load` (safe, no aliases); an
    unreadable file or invalid YAML raises ``error`` with one line naming ``what`` (e.g.
    ``"layout"``) and ``path:line:column``. The file enters the cache key of the stage reading it
    (:func:`runner.depends.depends_on`): a bundled layout named by a pack or a parameter is
    outside every input the runner hashes."""
    depends_on(path)
    try:
        return safe_yaml.load(safe_yaml.read_text(path))
    except OSError as exc:
        raise error(f"{what} {path}: cannot read {noun} ({exc.strerror or exc})") from None
    except yaml.YAMLError as exc:
        where = safe_yaml.error_position(exc, path)
        raise error(f"{what} {where}: not valid YAML ({safe_yaml.error_message(exc)})") from None


def parse_layout(data: Any, *, source: str = "<layout>") -> Layout:
    """Validate the mapping read from a layout file and build the :class:`Layout`.

    ``source`` names the file in error messages.
    """

    def fail(field: str, msg: str) -> StageError:
        return StageError(f"layout {source}: field '{field}': {msg}")

    if not isinstance(data, dict):
        raise StageError(f"layout {source}: expected a mapping at the top level")
    for key in ("name", "points", "subregions", "no_blend", "feature_point_sets", "rigid", "tracked"):
        if key not in data:
            raise fail(key, "missing")
    names = data["points"]
    if not isinstance(names, list) or not names or not all(isinstance(n, str) and n for n in names):
        raise fail("points", "expected a non-empty list of point names")
    seen: set[str] = set()
    for n in names:
        if n in seen:
            raise fail("points", f"duplicate point name {n!r}")
        seen.add(n)
    where = {n: i for i, n in enumerate(names)}

    def refs(value: Any, field: str, *, min_len: int = 0) -> tuple[int, ...]:
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise fail(field, "expected a list of point names")
        unknown = [v for v in value if v not in where]
        if unknown:
            raise fail(field, f"unknown point name {unknown[0]!r}")
        if len(set(value)) != len(value):
            raise fail(field, "a point is listed twice")
        if len(value) < min_len:
            raise fail(field, f"expected at least {min_len} points, got {len(value)}")
        return tuple(where[v] for v in value)

    if not isinstance(data["subregions"], list) or not data["subregions"]:
        raise fail("subregions", "expected a non-empty list")
    subregions = []
    for k, s in enumerate(data["subregions"]):
        field = f"subregions[{k}]"
        if not isinstance(s, dict) or not isinstance(s.get("name"), str):
            raise fail(field, "expected a mapping with 'name', 'polygon', 'points'")
        field = f"subregions[{k}] ({s['name']})"
        polygon = refs(s.get("polygon"), f"{field}.polygon", min_len=3)
        inside = refs(s.get("points", []), f"{field}.points")
        if set(polygon) & set(inside):
            raise fail(f"{field}.points", "a point is both on the polygon and inside it")
        teeth = s.get("teeth", False)
        if not isinstance(teeth, bool):
            raise fail(f"{field}.teeth", "expected true or false")
        subregions.append(Subregion(s["name"], polygon, inside, teeth))
    sub_names = [s.name for s in subregions]
    if len(set(sub_names)) != len(sub_names):
        raise fail("subregions", "duplicate subregion name")
    if sum(s.teeth for s in subregions) > 1:
        raise fail("subregions", "more than one teeth subregion")

    no_blend = []
    for k, pair in enumerate(data["no_blend"] or []):
        if not (isinstance(pair, list) and len(pair) == 2 and all(p in sub_names for p in pair)):
            raise fail(f"no_blend[{k}]", f"expected a pair of subregion names, got {pair!r}")
        no_blend.append((pair[0], pair[1]))

    sets = []
    for k, f in enumerate(data["feature_point_sets"] or []):
        field = f"feature_point_sets[{k}]"
        if not isinstance(f, dict) or not isinstance(f.get("name"), str):
            raise fail(field, "expected a mapping with 'name', 'level', 'points'")
        if f.get("level") not in (0, 1, 2):
            raise fail(f"{field}.level", f"expected 0, 1 or 2, got {f.get('level')!r}")
        sets.append(FeaturePointSet(f["name"], f["level"], refs(f.get("points"), f"{field}.points", min_len=2)))
    if sum(f.level == 0 for f in sets) != 1:
        raise fail("feature_point_sets", "expected exactly one set at level 0")
    uncovered = set(range(len(names))) - {p for f in sets for p in f.points}
    if uncovered:
        raise fail("feature_point_sets", f"point {names[min(uncovered)]!r} is in no feature point set")

    rigid = refs(data["rigid"], "rigid", min_len=4)
    tracked = refs(data["tracked"], "tracked", min_len=3)
    return Layout(
        name=str(data["name"]),
        point_names=tuple(names),
        subregions=tuple(subregions),
        no_blend=tuple(no_blend),
        feature_point_sets=tuple(sets),
        rigid=rigid,
        tracked=tracked,
    )


def subregion_mask(layout: Layout, points: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Rasterize the subregions of one face into an index mask (the mask image of Sec. 5.3).

    Polygons are painted in layout order, later subregions over earlier ones (so the eyes paint
    over their eye zones and the teeth subregion over the lips).

    Parameters
    ----------
    layout
        The layout.
    points
        ``(N, 2)`` float pixel positions of the feature points.
    size
        ``(W, H)`` of the mask in pixels.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` int16: the subregion index (position in ``layout.subregions``), -1 outside.
    """
    import cv2

    points = np.asarray(points, dtype=np.float64)
    if points.shape != (layout.n_points, 2):
        raise ValueError(f"expected points of shape ({layout.n_points}, 2), got {points.shape}")
    width, height = size
    mask = np.full((height, width), -1, dtype=np.int16)
    shift = 4
    for k, s in enumerate(layout.subregions):
        poly = np.round(points[list(s.polygon)] * (1 << shift)).astype(np.int32)
        cv2.fillPoly(mask, [poly], color=k, lineType=cv2.LINE_8, shift=shift)
    return mask
