"""Actor pack loader and validator: the example images of one target face (Zhang et al. 2006, Sec. 5, 8, 10, 12.1).

An actor pack is a folder with a manifest ``pack.yaml`` (format in ``docs/fixtures.md``):

- ``layout``: a bundled layout name (``zhang134``) or a layout file path relative to the pack;
- ``image_size``: ``[W, H]`` in pixels, shared by every image of the pack;
- ``intrinsics``: the 3x3 camera matrix A of eq. 10 (pixels), inline;
- ``model3d``: a CSV ``name,x,y,z`` (mm, head frame), the generic face model of Sec. 12.1;
- ``neutral``, ``standard``: ``{image: PNG, points: CSV}``, optionally ``matte: PNG`` (8-bit grey, the
  image's size: 255 where the pixel is real, 0 where the source did not hold it; no matte = every
  pixel real); the standard image has the mouth open;
- ``examples``, ``teeth_examples``: lists of ``{name, image, points}`` (Sec. 6 and Sec. 8);
- ``captured``: the 30-40 captured geometries for PCA (Sec. 10, 14), either an ``.npz`` with key
  ``points`` ``(K, N, 2)`` or a list of points files;
- ``source`` (optional, packs built from footage): ``{size: [W, H], scale: s}``, the footage's frame
  size and the neutral's scale, pack px per footage px (above 1: the images enlarge the footage).

Bounds, checked before anything large is read: ``image_size`` at most :data:`MAX_PACK_PIXELS`
pixels, each image's size read from its header (PNG, JPEG...) before it is decoded, at most
:data:`MAX_EXAMPLES` examples, :data:`MAX_TEETH_EXAMPLES` teeth examples and
:data:`MAX_CAPTURED` captured geometries (an ``.npz``'s array shape read from its header,
:mod:`stages.npz_file`). Example and teeth example names are unique (they name the data file's
columns), and no face's points may all lie on one point or one line parallel to an axis (a
degenerate geometry propagates as NaN).

A points file is a CSV with header ``name,x,y`` and one row per layout point (any order, every
name once), or an ``.npz`` with key ``points`` ``(N, 2)`` in layout order. Pixel coordinates have
their origin at the centre of the top-left pixel, x right, y down.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from runner.files import kind_problem
from runner.stage import StageError
from stages.image_header import ImageTooLarge, image_size
from stages.layout import Layout, load_layout, read_yaml
from stages.npz_file import NpzError, read_npz

MANIFEST = "pack.yaml"
FORMAT = "actor-pack/1"
MAX_PACK_PIXELS = 4096 * 4096  # image_size W x H (a pack holds ~20 images of that size, decoded)
MAX_EXAMPLES = 64  # example expressions (the paper: 10-15)
MAX_TEETH_EXAMPLES = 16
MAX_CAPTURED = 256  # captured geometries (the paper: 30-40)
MAX_FILE_BYTES = 256 << 20  # any one file of a pack (a 4096x4096 RGB PNG is under 50 MB)


class PackError(StageError):
    """An actor pack is missing a file or has a wrong field; the message names both."""


@dataclass
class Expression:
    """One face image with its feature points: ``image (H, W, 3) uint8`` RGB, ``points (N, 2) float64`` px,
    and its validity matte ``matte (H, W) uint8`` (255 = a real pixel; None: every pixel real)."""

    name: str
    image: np.ndarray
    points: np.ndarray
    matte: np.ndarray | None = None


@dataclass
class ActorPack:
    """A loaded, validated actor pack (see the module docstring for the files behind each field).

    ``captured_points`` is ``(K, N, 2)`` px; ``model3d`` ``(N, 3)`` mm in the head frame;
    ``intrinsics`` the ``(3, 3)`` matrix A of eq. 10; ``image_size`` is ``(W, H)``; ``source_scale``
    pack px per footage px (None: not built from footage).
    """

    path: Path
    name: str
    layout: Layout
    neutral: Expression
    standard: Expression
    examples: list[Expression]
    teeth_examples: list[Expression]
    captured_points: np.ndarray
    model3d: np.ndarray
    intrinsics: np.ndarray
    image_size: tuple[int, int]
    source_scale: float | None = None


def load_pack(path: str | Path) -> ActorPack:
    """Load an actor pack folder (or its ``pack.yaml``) and validate every file it names.

    Raises
    ------
    PackError
        Missing or unreadable file, image of the wrong size, wrong point count for the layout,
        unknown or missing point name, points outside the image, bad intrinsics; the message
        names the file and the field.
    """
    return _reader(path, decode=True).read()


def check_pack(path: str | Path) -> None:
    """Validate an actor pack as :func:`load_pack` does, every file it names included, reading
    each image's header but decoding no image (what a run checks before it starts).

    Raises
    ------
    StageError
        As :func:`load_pack` (a :class:`PackError`, or the layout's error), for all but an image
        body that cannot be decoded.
    """
    _reader(path, decode=False).read()


def _reader(path: str | Path, *, decode: bool) -> _PackReader:
    """The reader of the pack at ``path`` (a folder or its ``pack.yaml``), its manifest read."""
    path = Path(path)
    manifest = path if path.is_file() else path / MANIFEST
    data = read_yaml(manifest, what="actor pack", noun="manifest", error=PackError)
    return _PackReader(manifest.parent, manifest, data, decode=decode)


class _PackReader:
    """Reads one pack; ``fail`` builds the error naming the file and the field. With ``decode``
    False, images are checked from their headers and left undecoded (empty arrays)."""

    def __init__(self, root: Path, manifest: Path, data: Any, *, decode: bool) -> None:
        self.root = root
        self.manifest = manifest
        self.decode = decode
        if not isinstance(data, dict):
            raise PackError(f"actor pack {manifest}: expected a mapping at the top level")
        self.data = data

    def fail(self, file: Path | str, field: str, msg: str) -> PackError:
        return PackError(f"actor pack {file}: field '{field}': {msg}")

    def field(self, key: str) -> Any:
        if key not in self.data:
            raise self.fail(self.manifest, key, "missing")
        return self.data[key]

    def file(self, value: Any, field: str) -> Path:
        """The pack file named by ``value``; it must lie inside the pack folder (the runner's
        key for a pack covers that folder's files only)."""
        if not isinstance(value, str) or not value:
            raise self.fail(self.manifest, field, "expected a file path relative to the pack")
        path = self.root / value
        if Path(value).is_absolute() or not path.resolve().is_relative_to(self.root.resolve()):
            raise self.fail(self.manifest, field, f"{value!r} is outside the pack folder {self.root}")
        problem = kind_problem(path)
        if problem == "no such file":
            raise self.fail(self.manifest, field, f"file not found: {path}")
        if problem:
            raise self.fail(self.manifest, field, f"{path}: {problem}")
        if path.stat().st_size > MAX_FILE_BYTES:
            raise self.fail(self.manifest, field, f"{path}: larger than the {MAX_FILE_BYTES} bytes a pack file may have")
        return path

    def read(self) -> ActorPack:
        fmt = self.data.get("format", FORMAT)
        if fmt != FORMAT:
            raise self.fail(self.manifest, "format", f"expected {FORMAT!r}, got {fmt!r}")
        layout_ref = self.field("layout")
        if not isinstance(layout_ref, str) or not layout_ref:
            raise self.fail(self.manifest, "layout", "expected a layout name or file path")
        bundled = "/" not in layout_ref and not Path(layout_ref).suffix and not (self.root / layout_ref).exists()
        self.layout = load_layout(layout_ref if bundled else self.file(layout_ref, "layout"))
        size = self.field("image_size")
        if not (
            isinstance(size, list)
            and len(size) == 2
            and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in size)
        ):
            raise self.fail(self.manifest, "image_size", f"expected [W, H] positive integers, got {size!r}")
        if size[0] * size[1] > MAX_PACK_PIXELS:
            raise self.fail(
                self.manifest,
                "image_size",
                f"{size[0]}x{size[1]} is more than the {MAX_PACK_PIXELS} pixels a pack image may have",
            )
        self.size = (size[0], size[1])
        intrinsics = self.intrinsics()
        model3d = self.model3d()
        neutral = self.expression(self.field("neutral"), "neutral", "neutral")
        standard = self.expression(self.field("standard"), "standard", "standard")
        examples = self.expressions("examples", min_count=2, max_count=MAX_EXAMPLES)
        teeth = self.expressions("teeth_examples", min_count=1, max_count=MAX_TEETH_EXAMPLES)
        names = [e.name for e in examples + teeth]
        repeated = next((n for n in names if names.count(n) > 1), None)
        if repeated is not None:
            raise self.fail(
                self.manifest,
                "examples",
                f"name {repeated!r} is given to two examples (the names of examples and teeth examples must differ)",
            )
        captured = self.captured()
        return ActorPack(
            path=self.root,
            name=str(self.data.get("name", self.root.name)),
            layout=self.layout,
            neutral=neutral,
            standard=standard,
            examples=examples,
            teeth_examples=teeth,
            captured_points=captured,
            model3d=model3d,
            intrinsics=intrinsics,
            image_size=self.size,
            source_scale=self.source_scale(),
        )

    def source_scale(self) -> float | None:
        source = self.data.get("source")
        if source is None:
            return None
        scale = source.get("scale") if isinstance(source, dict) else None
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not scale > 0:
            raise self.fail(self.manifest, "source.scale", f"expected a positive number, got {scale!r}")
        return float(scale)

    def intrinsics(self) -> np.ndarray:
        value = self.field("intrinsics")
        try:
            a = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise self.fail(self.manifest, "intrinsics", "expected a 3x3 list of numbers") from None
        if a.shape != (3, 3):
            raise self.fail(self.manifest, "intrinsics", f"expected a 3x3 matrix, got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            row, col = np.argwhere(~np.isfinite(a))[0]
            raise self.fail(self.manifest, f"intrinsics[{row}][{col}]", f"expected a finite number, got {a[row, col]}")
        if a[0, 0] <= 0 or a[1, 1] <= 0 or not np.allclose(a[2], (0, 0, 1)) or a[1, 0] != 0:
            raise self.fail(self.manifest, "intrinsics", "expected [[fx, s, u0], [0, fy, v0], [0, 0, 1]] with fx, fy > 0")
        return a

    def model3d(self) -> np.ndarray:
        path = self.file(self.field("model3d"), "model3d")
        return self.named_rows(path, "model3d", ("x", "y", "z"))

    def named_rows(self, path: Path, field: str, columns: tuple[str, ...]) -> np.ndarray:
        """Read a CSV ``name,<columns>`` into ``(N, len(columns))`` in layout order."""
        try:
            with path.open(newline="", encoding="utf-8") as fh:
                rows = list(csv.reader(fh))
        except (OSError, UnicodeDecodeError) as exc:
            raise self.fail(path, field, f"cannot read CSV ({exc})") from None
        header = ["name", *columns]
        if not rows or [h.strip() for h in rows[0]] != header:
            raise self.fail(path, field, f"expected header {','.join(header)}")
        body = rows[1:]
        n = self.layout.n_points
        if len(body) != n:
            raise self.fail(path, field, f"expected {n} points for layout {self.layout.name!r}, got {len(body)}")
        out = np.full((n, len(columns)), np.nan)
        for k, row in enumerate(body, start=2):
            if len(row) != len(header):
                raise self.fail(path, field, f"line {k}: expected {len(header)} values")
            try:
                index = self.layout.index(row[0].strip())
            except KeyError:
                raise self.fail(path, field, f"line {k}: unknown point name {row[0]!r}") from None
            try:
                out[index] = [float(v) for v in row[1:]]
            except ValueError:
                raise self.fail(path, field, f"line {k}: not a number") from None
        missing = np.flatnonzero(np.isnan(out).any(axis=1))
        if missing.size:
            raise self.fail(path, field, f"point {self.layout.point_names[missing[0]]!r} missing or not finite")
        if not np.all(np.isfinite(out)):
            raise self.fail(path, field, "values must be finite")
        if columns == ("x", "y"):
            self.check_spread(out, path, field)
        return out

    def points(self, path: Path, field: str) -> np.ndarray:
        if path.suffix == ".npz":
            pts = self.npz_points(path, field, faces=1)
        else:
            pts = self.named_rows(path, field, ("x", "y"))
        self.check_inside(pts, path, field)
        return pts

    def npz_points(self, path: Path, field: str, *, faces: int) -> np.ndarray:
        """Array ``points`` of an ``.npz``: ``(N, 2)`` or ``(K, N, 2)``, at most ``faces`` faces
        (its header checked before it is read)."""
        n = self.layout.n_points
        try:
            arrays = read_npz(path, ["points"], max_values=faces * n * 2)
        except NpzError as exc:
            raise self.fail(path, field, f"{exc} (at most {faces} face(s) of {n} points)") from None
        if "points" not in arrays:
            raise self.fail(path, field, "npz has no array 'points'")
        pts = np.asarray(arrays["points"], dtype=np.float64)
        if pts.ndim < 2 or pts.shape[-2:] != (n, 2):
            raise self.fail(
                path, field, f"expected points of shape (..., {n}, 2) for layout {self.layout.name!r}, got {pts.shape}"
            )
        if not np.all(np.isfinite(pts)):
            raise self.fail(path, field, "points must be finite")
        self.check_spread(pts, path, field)
        return pts

    def check_spread(self, pts: np.ndarray, path: Path, field: str) -> None:
        """Refuse a face whose points all lie on one point or on one line parallel to an axis."""
        faces = pts.reshape(-1, self.layout.n_points, 2)
        flat = np.flatnonzero((np.ptp(faces, axis=1) <= 1e-9).any(axis=1))
        if flat.size:
            which = f"face {flat[0]}: " if len(faces) > 1 else ""
            raise self.fail(
                path, field, f"{which}its {self.layout.n_points} points all coincide or lie on one horizontal or vertical line"
            )

    def check_inside(self, pts: np.ndarray, path: Path, field: str) -> None:
        w, h = self.size
        flat = pts.reshape(-1, 2)
        bad = (flat[:, 0] < -0.5) | (flat[:, 0] > w - 0.5) | (flat[:, 1] < -0.5) | (flat[:, 1] > h - 0.5)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            name = self.layout.point_names[k % self.layout.n_points]
            x, y = flat[k]
            raise self.fail(path, field, f"point {name!r} at ({x:.1f}, {y:.1f}) is outside the {w}x{h} image")

    def check_header(self, path: Path, field: str, what: str) -> None:
        """Refuse image file ``path`` unless its header declares the manifest's ``image_size``
        (at most :data:`MAX_PACK_PIXELS`) and its PNG chunks are whole: checked before it is
        decoded, as decoding allocates whatever size the header declares."""
        try:
            header = image_size(path, max_pixels=MAX_PACK_PIXELS, verify=True)
        except ImageTooLarge as exc:
            raise self.fail(path, field, f"{what} is {exc}") from None
        if header is None:
            raise self.fail(path, field, "cannot read image (not a PNG, JPEG, TIFF or WebP file)")
        if header != self.size:
            raise self.fail(
                path, field, f"{what} is {header[0]}x{header[1]}, the manifest's image_size is {self.size[0]}x{self.size[1]}"
            )

    def image(self, path: Path, field: str) -> np.ndarray:
        import cv2

        self.check_header(path, field, "image")
        if not self.decode:
            return np.zeros((0, 0, 3), np.uint8)
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None:
            raise self.fail(path, field, "cannot read image")
        h, w = img.shape[:2]
        if (w, h) != self.size:
            raise self.fail(path, field, f"image is {w}x{h}, the manifest's image_size is {self.size[0]}x{self.size[1]}")
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)

    def expression(self, entry: Any, field: str, default_name: str) -> Expression:
        if not isinstance(entry, dict):
            raise self.fail(self.manifest, field, "expected a mapping with 'image' and 'points'")
        image = self.image(self.file(entry.get("image"), f"{field}.image"), f"{field}.image")
        points = self.points(self.file(entry.get("points"), f"{field}.points"), f"{field}.points")
        if points.ndim != 2:
            raise self.fail(self.manifest, f"{field}.points", "expected one face's points (N, 2)")
        matte = None
        if entry.get("matte") is not None:
            matte = self.matte(self.file(entry["matte"], f"{field}.matte"), f"{field}.matte")
        return Expression(name=str(entry.get("name", default_name)), image=image, points=points, matte=matte)

    def matte(self, path: Path, field: str) -> np.ndarray:
        import cv2

        self.check_header(path, field, "matte")
        if not self.decode:
            return np.zeros((0, 0), np.uint8)
        matte = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if matte is None:
            raise self.fail(path, field, "cannot read image")
        if matte.ndim != 2 or matte.dtype != np.uint8:
            raise self.fail(path, field, f"expected an 8-bit grey PNG, got shape {matte.shape} {matte.dtype}")
        h, w = matte.shape
        if (w, h) != self.size:
            raise self.fail(path, field, f"matte is {w}x{h}, the manifest's image_size is {self.size[0]}x{self.size[1]}")
        return matte

    def expressions(self, key: str, *, min_count: int, max_count: int) -> list[Expression]:
        entries = self.field(key)
        if not isinstance(entries, list) or not min_count <= len(entries) <= max_count:
            got = f"{len(entries)} given" if isinstance(entries, list) else f"got {type(entries).__name__}"
            raise self.fail(self.manifest, key, f"expected a list of {min_count} to {max_count} expressions, {got}")
        return [self.expression(e, f"{key}[{k}]", f"{key}_{k}") for k, e in enumerate(entries)]

    def captured(self) -> np.ndarray:
        value = self.field("captured")
        if isinstance(value, list):
            if len(value) > MAX_CAPTURED:
                raise self.fail(self.manifest, "captured", f"{len(value)} captured geometries, at most {MAX_CAPTURED}")
            pts = np.stack([self.points(self.file(v, f"captured[{k}]"), f"captured[{k}]") for k, v in enumerate(value)])
        else:
            path = self.file(value, "captured")
            pts = self.npz_points(path, "captured", faces=MAX_CAPTURED)
            self.check_inside(pts, path, "captured")
        if pts.ndim != 3 or pts.shape[0] < 2:
            raise self.fail(self.manifest, "captured", f"expected at least 2 captured geometries (K, N, 2), got {pts.shape}")
        return pts
