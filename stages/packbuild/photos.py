"""A folder of photos as a frame source for the pack builder (``pack_build_photos.yaml``):
``photos.decode`` (the photos as frames, as ``video.decode`` gives a clip's) and
``photos.identity`` (a warning naming the photos of another person).

Which files: the image files directly in the folder (suffix ``.jpg .jpeg .png .tif .tiff .webp``,
any case), sorted by file name (code points: ``IMG_10`` before ``IMG_9``); other files,
sub-folders and hidden files (name starting with ``.``) are ignored. Frame ``t`` is the ``t``-th
readable photo in that order. A photo whose header declares more than :data:`MAX_PHOTO_PIXELS`
pixels is skipped before it is decoded (:mod:`stages.image_header`), and so is one that OpenCV
cannot decode, with one warning line counting them and naming the first few
(:data:`NAMED_FILES`); a folder with no readable photo is an error.

Orientation: OpenCV's decoder applies the EXIF Orientation tag (1-8) of JPEG, PNG, TIFF and
WebP files, so a phone's portrait photo stored as landscape pixels comes out upright.

One frame size (:func:`frame_size`, :func:`letterbox`): the largest upright width and the largest
upright height over the photos, scaled down (aspect kept) so that the longer side is at most
``max_side``. Each photo is scaled uniformly to fit that frame (area averaging when shrinking,
bilinear when enlarging, untouched when it already has the frame's size), centred, and the
border filled by replicating the photo's edge pixels (as ``pack.write`` fills outside a frame).
A photo point ``(x, y)`` lands at ``(sx x + tx, sy y + ty)`` (:func:`photo_to_frame`).
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from runner.files import kind_problem
from runner.stage import Context, FrameStage, Param, SequenceStage, StageError, StreamInfo
from stages.landmarks.bundles import LANDMARKS
from stages.packbuild.bundles import PHOTO_IDENTITY
from stages.image_header import ImageTooLarge, image_size
from stages.packbuild.identity import DIFFERENT_FACE_DISTANCE, face_signature, majority_outliers

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".webp")
MAX_PHOTO_PIXELS = 100_000_000  # a larger photo is skipped undecoded (100 MP: 300 MB as 8-bit RGB)
NAMED_FILES = 5  # files named in a warning line; the others are counted
PHOTO_FPS = 1.0  # the frame rate the photos are given: one photo per second (time_s = frame index)
DEFAULT_MAX_SIDE = 1920


@dataclass(frozen=True)
class PhotoSet:
    """The readable photos of a folder, in frame order.

    ``paths`` the readable photos; ``sizes`` their upright ``(width, height)`` in px;
    ``unreadable`` the image files OpenCV could not decode; ``too_large`` those skipped
    undecoded, with their header's size (``"30000x30000 px, ..."``); ``frame_size`` ``(W, H)``
    of the frames (:func:`frame_size`).
    """

    paths: tuple[Path, ...]
    sizes: tuple[tuple[int, int], ...]
    unreadable: tuple[Path, ...]
    too_large: tuple[tuple[Path, str], ...]
    frame_size: tuple[int, int]

    def skipped(self) -> str | None:
        """One line counting and naming (the first :data:`NAMED_FILES` of each kind) the files
        skipped, or None."""
        parts = []
        if self.unreadable:
            parts.append(f"{len(self.unreadable)} unreadable image files skipped: {_named([p.name for p in self.unreadable])}")
        if self.too_large:
            sizes = [f"{path.name} ({why.split(', ')[0]})" for path, why in self.too_large]
            parts.append(
                f"{len(self.too_large)} image files of more than {MAX_PHOTO_PIXELS} px skipped undecoded: {_named(sizes)}"
            )
        return "; ".join(parts) or None


def _named(names: list[str]) -> str:
    """The first :data:`NAMED_FILES` of ``names``, and how many more."""
    more = f" and {len(names) - NAMED_FILES} more" if len(names) > NAMED_FILES else ""
    return ", ".join(names[:NAMED_FILES]) + more


def list_photos(folder: Path) -> list[Path]:
    """The image files directly in ``folder`` (by suffix, case-insensitive; hidden files and
    sub-folders left out), sorted by file name. Raises ValueError for a folder that is not one,
    or an image file that is not a regular file (a link to ``/dev/zero``, a FIFO, a broken link:
    :func:`runner.files.kind_problem`), naming it and saying what it is."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"expected a folder of photos, got {folder} (not a folder)")
    named = [p for p in folder.iterdir() if not p.name.startswith(".") and p.suffix.lower() in PHOTO_SUFFIXES]
    photos = sorted((p for p in named if not p.is_dir()), key=lambda p: p.name)
    for path in photos:
        problem = kind_problem(path)
        if problem:
            raise ValueError(f"{path}: {problem}")
    return photos


def read_photo(path: Path) -> np.ndarray | None:
    """The photo upright (EXIF orientation applied) as ``(H, W, 3)`` uint8 RGB, or None when the
    file cannot be read or decoded. Grey and 16-bit images are converted (16 bits: the high byte);
    an alpha channel is dropped; of a multi-page TIFF the first page.

    Raises
    ------
    ImageTooLarge
        Its header declares more than :data:`MAX_PHOTO_PIXELS` pixels (nothing is decoded).
    """
    import cv2

    if image_size(path, max_pixels=MAX_PHOTO_PIXELS, verify=True) is None:
        return None
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError:
        return None
    bgr = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    return None if bgr is None else cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def frame_size(sizes: list[tuple[int, int]] | tuple[tuple[int, int], ...], *, max_side: int) -> tuple[int, int]:
    """The frame size ``(W, H)`` for photos of upright ``sizes`` ``[(w, h), ...]`` px: ``W = max
    w``, ``H = max h``, both multiplied by ``min(1, max_side / max(W, H))`` and rounded."""
    if not sizes:
        raise ValueError("expected at least one photo size, got none")
    if max_side < 1:
        raise ValueError(f"max_side: expected a side >= 1 px, got {max_side}")
    width, height = max(w for w, _ in sizes), max(h for _, h in sizes)
    shrink = min(1.0, max_side / max(width, height))
    return max(1, round(width * shrink)), max(1, round(height * shrink))


def _fitted(size: tuple[int, int], frame: tuple[int, int]) -> tuple[int, int, int, int]:
    """``(w', h', ox, oy)``: the photo's size scaled uniformly to fit ``frame`` and its offset."""
    (w, h), (width, height) = size, frame
    scale = min(width / w, height / h)
    fw, fh = min(width, max(1, round(w * scale))), min(height, max(1, round(h * scale)))
    return fw, fh, (width - fw) // 2, (height - fh) // 2


def photo_to_frame(size: tuple[int, int], frame: tuple[int, int]) -> np.ndarray:
    """The map of a photo's pixel coordinates into its frame (:func:`letterbox`).

    Parameters
    ----------
    size
        The photo's upright ``(w, h)``, px.
    frame
        The frame size ``(W, H)``, px.

    Returns
    -------
    numpy.ndarray
        ``(4,)`` = ``(sx, sy, tx, ty)``: ``x' = sx x + tx``, ``y' = sy y + ty`` (pixel centres at
        integer coordinates: ``sx = w'/w``, ``tx = ox + (sx - 1) / 2``, likewise in y).
    """
    fw, fh, ox, oy = _fitted(size, frame)
    sx, sy = fw / size[0], fh / size[1]
    return np.array([sx, sy, ox + (sx - 1) / 2, oy + (sy - 1) / 2])


def placed(size: tuple[int, int], frame: tuple[int, int]) -> np.ndarray:
    """``(H, W, 1) uint8``: 255 on the pixels of ``frame = (W, H)`` a photo of ``size = (w, h)``
    covers once :func:`letterbox` placed it, 0 on the border it filled (not the photo's pixels)."""
    fw, fh, ox, oy = _fitted(size, frame)
    valid = np.zeros((frame[1], frame[0], 1), np.uint8)
    valid[oy : oy + fh, ox : ox + fw] = 255
    return valid


def letterbox(rgb: np.ndarray, frame: tuple[int, int]) -> np.ndarray:
    """``rgb (h, w, 3)`` uint8 scaled uniformly to fit ``frame = (W, H)``, centred, the border
    filled by replicating the edge pixels (for the landmarker; :func:`placed` marks it): ``(H, W,
    3)`` uint8 (the same array when it already has the frame's size)."""
    import cv2

    h, w = rgb.shape[:2]
    fw, fh, ox, oy = _fitted((w, h), frame)
    if (fw, fh) != (w, h):
        shrinking = fw < w or fh < h
        rgb = cv2.resize(rgb, (fw, fh), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR)
    if (fw, fh) == frame:
        return rgb
    return cv2.copyMakeBorder(rgb, oy, frame[1] - fh - oy, ox, frame[0] - fw - ox, cv2.BORDER_REPLICATE)


def scan_photos(folder: Path, *, max_side: int = DEFAULT_MAX_SIDE) -> PhotoSet:
    """Which image files of ``folder`` are readable, their upright sizes and the frame size.
    Every file is decoded once per process while it is unchanged (name, size and modification
    time): ``photos.decode`` and ``photos.identity`` both scan the folder. Raises ValueError
    when the folder holds no readable photo (naming the unreadable files, or the suffixes
    looked for)."""
    state = tuple((path, *_stamp(path)) for path in list_photos(folder))
    readable, sizes, unreadable, too_large = _decode_all(state)
    photos = PhotoSet(readable, sizes, unreadable, too_large, (0, 0))
    if not readable:
        if unreadable or too_large:
            names = sorted([p.name for p in unreadable] + [p.name for p, _ in too_large])
            raise ValueError(f"{folder}: none of its {len(names)} image files could be read ({_named(names)})")
        raise ValueError(f"{folder}: no photos in it (looked for {' '.join(PHOTO_SUFFIXES)})")
    return replace(photos, frame_size=frame_size(sizes, max_side=max_side))


def _stamp(path: Path) -> tuple[int, int]:
    """``(size, mtime_ns)`` of a file: a photo changed in place is decoded again."""
    stat = path.stat()
    return stat.st_size, stat.st_mtime_ns


@functools.lru_cache(maxsize=4)
def _decode_all(
    state: tuple[tuple[Path, int, int], ...],
) -> tuple[tuple[Path, ...], tuple[tuple[int, int], ...], tuple[Path, ...], tuple[tuple[Path, str], ...]]:
    """Decode the files of ``state`` (path, size, mtime_ns): the readable ones, their upright
    ``(width, height)``, the unreadable ones and those too large to decode (with why)."""
    readable, sizes, unreadable, too_large = [], [], [], []
    for path, _, _ in state:
        try:
            rgb = read_photo(path)
        except ImageTooLarge as exc:
            too_large.append((path, str(exc)))
            continue
        if rgb is None:
            unreadable.append(path)
        else:
            readable.append(path)
            sizes.append((rgb.shape[1], rgb.shape[0]))
    return tuple(readable), tuple(sizes), tuple(unreadable), tuple(too_large)


def _scan(stage: str, folder: Path, max_side: int) -> PhotoSet:
    """:func:`scan_photos` for a stage: an unusable folder is a :class:`StageError`."""
    try:
        return scan_photos(folder, max_side=max_side)
    except ValueError as exc:
        raise StageError(f"{stage}: input 'photos': {exc}") from None


class PhotosDecode(FrameStage):
    """``photos.decode``: the photos of a folder as frames ``(B, H, W, 3)`` uint8 RGB, the
    stream ``video.decode`` gives for a clip (module docstring: which files, orientation, frame
    size). Not cached (decoding is cheaper than reading raw frames back); the runner's digest of
    a ``dir`` input covers every file's bytes, so adding, removing or editing a photo re-runs
    everything downstream."""

    name = "photos.decode"
    version = "2"
    doc = "Decode a folder of photos (jpg, png, tif, webp; EXIF orientation) into RGB uint8 frames of one size"
    inputs = {"photos": "dir"}
    outputs = {"frames": "frames", "valid": "frames"}
    cached = False
    params = (
        Param("max_side", int, DEFAULT_MAX_SIDE, "longest side of the frames, px (larger photos are shrunk)", min=64, max=16384),
    )

    def __init__(self) -> None:
        self._scanned: tuple[Path, int, PhotoSet] | None = None

    @classmethod
    def check_input(cls, port: str, path: Path) -> str | None:
        """Each image file of the folder is a regular file (:func:`list_photos`), checked
        before a run starts."""
        try:
            list_photos(path)
        except ValueError as exc:
            return str(exc)
        return None

    def photos(self, folder: Path, max_side: int) -> PhotoSet:
        """The folder's :class:`PhotoSet`, scanned once per stage instance; the files skipped
        are counted in one warning line (:meth:`PhotoSet.skipped`)."""
        if self._scanned is None or self._scanned[:2] != (folder, max_side):
            photos = _scan(self.name, folder, max_side)
            if photos.skipped():
                logging.getLogger(f"runner.stage.{self.name}").warning("warning: %s: %s: %s", self.name, folder, photos.skipped())
            self._scanned = (folder, max_side, photos)
        return self._scanned[2]

    def stream_info(self, inputs: Mapping[str, Any], params: Mapping[str, Any]) -> StreamInfo:
        photos = self.photos(Path(inputs["photos"]), int(params.get("max_side", DEFAULT_MAX_SIDE)))
        width, height = photos.frame_size
        return StreamInfo(frames=len(photos.paths), fps=PHOTO_FPS, width=width, height=height)

    def process(
        self, start: int, stop: int, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context
    ) -> dict[str, Any]:
        """Photos ``[start, stop)`` as frames ``(stop - start, H, W, 3)`` uint8 RGB, and ``valid``
        ``(stop - start, H, W, 1)`` uint8: 255 where the frame's pixel is the photo's (:func:`placed`)."""
        photos = self.photos(Path(inputs["photos"]), int(params.get("max_side", DEFAULT_MAX_SIDE)))
        frames, valid = [], []
        for path in photos.paths[start:stop]:
            rgb = read_photo(path)
            if rgb is None:
                raise StageError(f"{self.name}: {path}: could not be read any more (changed during the run?)")
            frames.append(letterbox(rgb, photos.frame_size))
            valid.append(placed((rgb.shape[1], rgb.shape[0]), photos.frame_size))
        return {"frames": np.stack(frames), "valid": np.stack(valid)}


class PhotoIdentity(SequenceStage):
    """``photos.identity``: warns, counting them and naming the first :data:`NAMED_FILES`, about
    the photos whose face shape differs from the majority's (:mod:`stages.packbuild.identity`, a
    coarse check of proportions).

    Output bundle ``photo_identity``: ``names (T,) str`` the photos' file names in frame order,
    ``distance (T,) f8`` each face's signature distance to the majority's (NaN without a face),
    ``differs (T,) bool``, ``max_distance ()``.
    """

    name = "photos.identity"
    version = "1"
    doc = "warn about photos of a folder whose face shape (rigid landmark proportions) differs from the majority's"
    inputs = {"photos": "dir", "landmarks": LANDMARKS}
    outputs = {"identity": PHOTO_IDENTITY}
    params = (
        Param(
            "max_distance",
            float,
            DIFFERENT_FACE_DISTANCE,
            "signature distance above which a face is named as another person's",
            min=1e-6,
            max=10.0,
        ),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        # which photos are frames does not depend on photos.decode's max_side (the frame size does)
        photos = _scan(self.name, Path(inputs["photos"]), DEFAULT_MAX_SIDE)
        names = [p.name for p in photos.paths]
        landmarks = inputs["landmarks"]
        for key in ("xy", "z"):
            if key not in landmarks:
                raise StageError(f"{self.name}: input 'landmarks': missing key '{key}'")
        if len(landmarks["xy"]) != len(names):
            raise StageError(
                f"{self.name}: input 'landmarks' has {len(landmarks['xy'])} frames, the folder {len(names)} readable photos"
            )
        threshold = float(params.get("max_distance", DIFFERENT_FACE_DISTANCE))
        try:
            distance, differs = majority_outliers(face_signature(landmarks["xy"], landmarks["z"]), threshold=threshold)
        except ValueError as exc:
            raise StageError(f"{self.name}: input 'landmarks': {exc}") from None
        faces = int(np.isfinite(distance).sum())
        if differs.any():
            named = _named([f"{names[t]} (frame {t}, {distance[t]:.3f})" for t in np.flatnonzero(differs)])
            ctx.log.warning(
                "warning: %s: %d of %d faces may be another person's (face-shape distance to the "
                "majority above %.3f; a coarse check): %s",
                self.name,
                int(differs.sum()),
                faces,
                threshold,
                named,
            )
        else:
            ctx.log.info(
                "%s: the %d faces look like one person (largest face-shape distance %.3f <= %.3f)",
                self.name,
                faces,
                float(np.nanmax(distance, initial=0.0)),
                threshold,
            )
        ctx.progress(len(names))
        return {
            "identity": {
                "names": np.array(names, dtype=str),
                "distance": distance,
                "differs": differs,
                "max_distance": np.float64(threshold),
            }
        }
