"""MediaPipe's Face Landmarker run frame by frame, with points in the project's pixel convention.

The Face Landmarker (Google, Apache-2.0; ``models/NOTICE``) finds faces with a short-range
detector, then fits its 478-vertex face mesh (468 face vertices + 2 x 5 iris points) to each, and
gives 52 blendshape scores and a 4x4 facial transformation matrix per face.

Pixel convention
----------------
MediaPipe returns landmarks normalized by the image size. ``x = x_norm * W`` and
``y = y_norm * H`` are already in the project's convention (origin at the centre of the top-left
pixel, OpenCV's): a face upscaled by s with ``cv2.resize`` (which maps pixel centres,
``x_s + 0.5 = s (x + 0.5)``) gives positions that fit ``x_s = s a + b`` with b close to -0.5 px,
what the centre convention predicts (a corner origin predicts b = 0), and a horizontally flipped
image's mesh mirrors about ``(W - 1) / 2``. ``tests/stages/landmarks/test_landmarker.py`` checks
the convention with the horizontal flip and a sub-pixel shift.

Depth ``z`` is MediaPipe's relative depth (smaller = nearer the camera, origin near the head's
centre) multiplied by the width of the image the face was found in, so it has the px scale of x.

Small faces
-----------
The detector only finds faces that fill much of its input (a face about 90 px wide is found on a
768 x 768 canvas and lost on 1024 x 1024). So :class:`Landmarker` searches, per frame and in order:

1. a square crop around the previous frame's face (``crop_scale`` x its larger bounding-box side);
2. the whole frame;
3. with ``search_tiles``, overlapping square tiles of half the frame's shorter side (stride half a
   tile), faces merged across tiles.

The first region with a face wins. Regions are whole-pixel crops, so positions map back by
adding the crop's offset. The landmark model works on its own fixed-size crop of the face, taken
from the detector's box, so the region changes the points only by the box's variation (a few
tenths of a px; the tests' shift checks bound it). After the first frame the crop around the
previous face is the cheap case, and the tiles find a small face that the whole frame misses; a
face below about 4 % of the frame's side is lost even by the tiles.

IMAGE mode, one independent call per frame, rather than MediaPipe's VIDEO mode (whole frame, its
own tracking and landmark smoothing): on still, noisy input IMAGE mode's points scatter less;
VIDEO mode's smoothing lowers the frame-to-frame jitter but lags, smoothing is left to the
pipeline's smoothing stages, and VIDEO mode cannot follow the crop's changing region.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

MODEL_PATH = Path(__file__).resolve().parent / "models" / "face_landmarker.task"
MODEL_SHA256 = "64184e229b263107bc2b804c6625db1341ff2bb731874b0bcc2fe6544e0bc9ff"

N_MESH = 478
"""Vertices of MediaPipe's face mesh with irises (468 face + 10 iris)."""

OUTER_EYE_CORNERS = (33, 263)
"""Mesh vertices of the outer eye corners (viewer's left, viewer's right in a frontal image)."""

BLENDSHAPE_NAMES = (
    "_neutral",
    "browDownLeft",
    "browDownRight",
    "browInnerUp",
    "browOuterUpLeft",
    "browOuterUpRight",
    "cheekPuff",
    "cheekSquintLeft",
    "cheekSquintRight",
    "eyeBlinkLeft",
    "eyeBlinkRight",
    "eyeLookDownLeft",
    "eyeLookDownRight",
    "eyeLookInLeft",
    "eyeLookInRight",
    "eyeLookOutLeft",
    "eyeLookOutRight",
    "eyeLookUpLeft",
    "eyeLookUpRight",
    "eyeSquintLeft",
    "eyeSquintRight",
    "eyeWideLeft",
    "eyeWideRight",
    "jawForward",
    "jawLeft",
    "jawOpen",
    "jawRight",
    "mouthClose",
    "mouthDimpleLeft",
    "mouthDimpleRight",
    "mouthFrownLeft",
    "mouthFrownRight",
    "mouthFunnel",
    "mouthLeft",
    "mouthLowerDownLeft",
    "mouthLowerDownRight",
    "mouthPressLeft",
    "mouthPressRight",
    "mouthPucker",
    "mouthRight",
    "mouthRollLower",
    "mouthRollUpper",
    "mouthShrugLower",
    "mouthShrugUpper",
    "mouthSmileLeft",
    "mouthSmileRight",
    "mouthStretchLeft",
    "mouthStretchRight",
    "mouthUpperUpLeft",
    "mouthUpperUpRight",
    "noseSneerLeft",
    "noseSneerRight",
)
"""The model's 52 blendshape categories in score order (ARKit names; subject's Left/Right)."""

SELECT_RULES = ("largest", "central")

_verified: dict[tuple[Path, int, int], None] = {}


def verify_model(path: str | Path = MODEL_PATH, *, sha256: str = MODEL_SHA256) -> Path:
    """Check the model file's SHA-256 (once per path, size and modification time).

    Raises
    ------
    ValueError
        The file is missing, unreadable, or its digest is not ``sha256`` (damaged or another
        model); the message names the file and both digests.
    """
    path = Path(path).resolve()
    try:
        stat = path.stat()
        key = (path, stat.st_size, stat.st_mtime_ns)
        if key not in _verified:
            digest = hashlib.sha256(path.read_bytes()).hexdigest()
            if digest != sha256:
                raise ValueError(
                    f"face landmarker model {path}: sha256 {digest}, expected {sha256} "
                    f"(damaged or replaced; see {path.parent / 'NOTICE'})"
                )
            _verified[key] = None
    except OSError as exc:
        raise ValueError(f"face landmarker model {path}: cannot read ({exc.strerror or exc})") from None
    return path


@dataclass(frozen=True)
class MeshFrame:
    """The face mesh of one frame.

    Attributes
    ----------
    xy
        ``(478, 2)`` float64 px, project convention (origin at the centre of the top-left pixel);
        NaN when not ``valid``.
    z
        ``(478,)`` float64 relative depth, px scale of x (smaller = nearer); NaN when not ``valid``.
    valid
        A face was found.
    blendshapes
        ``(52,)`` float32 scores in [0, 1] in :data:`BLENDSHAPE_NAMES` order; 0 when not ``valid``.
    matrix
        ``(4, 4)`` float64 facial transformation matrix (canonical face mesh -> MediaPipe's
        camera frame of the searched region, cm); identity when not ``valid``.
    faces
        Number of faces found in the searched region (the crop, the frame, or all tiles).
    region
        ``(4,)`` int ``x0, y0, width, height`` of the region the face was found in (the whole
        frame, a crop or a tile); the whole frame when not ``valid``.
    """

    xy: np.ndarray
    z: np.ndarray
    valid: bool
    blendshapes: np.ndarray
    matrix: np.ndarray
    faces: int
    region: np.ndarray


def crop_around(box: np.ndarray, *, scale: float, size: tuple[int, int]) -> np.ndarray:
    """A whole-pixel square region around a face box, shifted to lie inside the image.

    Parameters
    ----------
    box
        ``(4,)`` ``x0, y0, x1, y1`` px bounding box of the face.
    scale
        Side of the square as a multiple of the box's larger side.
    size
        ``(W, H)`` of the image.

    Returns
    -------
    numpy.ndarray
        ``(4,)`` int ``x0, y0, width, height``; clipped to the image where the square is larger.
    """
    width, height = size
    side = int(np.ceil(scale * max(box[2] - box[0], box[3] - box[1])))
    cw, ch = min(side, width), min(side, height)
    cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
    x0 = int(np.clip(round(cx - cw / 2), 0, width - cw))
    y0 = int(np.clip(round(cy - ch / 2), 0, height - ch))
    return np.array([x0, y0, cw, ch])


def tiles(size: tuple[int, int]) -> list[np.ndarray]:
    """Overlapping square tiles of half the image's shorter side, stride half a tile.

    Returns ``[(4,) int x0, y0, width, height, ...]`` covering the ``(W, H)`` image; the last
    tile of a row or column is flush with the image edge.
    """
    width, height = size
    side = min(width, height) // 2
    if side < 1:
        return []
    step = max(side // 2, 1)

    def starts(extent: int) -> list[int]:
        return sorted(set(list(range(0, extent - side, step)) + [extent - side]))

    return [np.array([x0, y0, side, side]) for y0 in starts(height) for x0 in starts(width)]


def _box(xy: np.ndarray) -> np.ndarray:
    return np.concatenate([xy.min(axis=0), xy.max(axis=0)])


def _overlap(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over the smaller box's area, of two ``x0, y0, x1, y1`` boxes."""
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    if w <= 0 or h <= 0:
        return 0.0
    smaller = min((a[2] - a[0]) * (a[3] - a[1]), (b[2] - b[0]) * (b[3] - b[1]))
    return float(w * h / smaller)


@contextlib.contextmanager
def native_logs_silenced() -> Iterator[None]:
    """Send file descriptor 2 to ``/dev/null`` for the block: MediaPipe's C++ side (absl, glog,
    TensorFlow Lite) prints start-up lines there ("All log messages before absl::InitializeLog()",
    "Created TensorFlow Lite XNNPACK delegate", a feedback-manager warning) that are not errors
    and that no environment variable of 0.10.31 turns off. Python exceptions are unaffected."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


class Landmarker:
    """MediaPipe Face Landmarker over a sequence of frames (IMAGE mode, one call per frame).

    Use as a context manager (``with Landmarker() as lm: lm.detect(rgb)``) or call
    :meth:`close`. Frames are searched in the previous face's crop, then the whole frame, then
    tiles (module docstring). MediaPipe's native start-up log lines are silenced
    (:func:`native_logs_silenced`).

    Parameters
    ----------
    model_path
        The ``.task`` bundle; its SHA-256 is checked against ``sha256``.
    max_faces
        Faces MediaPipe looks for per searched region.
    select
        Which face to keep when there are several: ``"largest"`` (bounding-box area) or
        ``"central"`` (box centre nearest the frame centre).
        The rule chooses a face when there is no previous one; after that the face overlapping
        the previous frame's face most is kept (the crop around it may hold another face, and a
        crop as large as the frame holds all of them), so the face chosen first is followed even
        if another becomes larger or more central. Where no face overlaps the previous one the
        rule chooses again.
    min_detection_confidence
        Detector score threshold.
    crop_scale
        Side of the crop around the previous face, in multiples of its larger box side; 0 turns
        the crop off.
    search_tiles
        Search tiles when neither the crop nor the whole frame has a face.
    """

    def __init__(
        self,
        *,
        model_path: str | Path = MODEL_PATH,
        sha256: str = MODEL_SHA256,
        max_faces: int = 4,
        select: str = "largest",
        min_detection_confidence: float = 0.5,
        crop_scale: float = 3.0,
        search_tiles: bool = True,
    ) -> None:
        if select not in SELECT_RULES:
            raise ValueError(f"select: expected one of {SELECT_RULES}, got {select!r}")
        if not isinstance(max_faces, int) or max_faces < 1:
            raise ValueError(f"max_faces: expected an integer >= 1, got {max_faces!r}")
        if not 0.0 <= min_detection_confidence <= 1.0:
            raise ValueError(f"min_detection_confidence: expected a value in [0, 1], got {min_detection_confidence}")
        if crop_scale != 0 and crop_scale < 1.0:
            raise ValueError(f"crop_scale: expected 0 (off) or >= 1, got {crop_scale}")
        path = verify_model(model_path, sha256=sha256)
        from mediapipe.tasks.python import BaseOptions, vision

        options = vision.FaceLandmarkerOptions(
            base_options=BaseOptions(model_asset_path=str(path)),
            running_mode=vision.RunningMode.IMAGE,
            num_faces=max_faces,
            output_face_blendshapes=True,
            output_facial_transformation_matrixes=True,
            min_face_detection_confidence=min_detection_confidence,
        )
        with native_logs_silenced():
            self._task = vision.FaceLandmarker.create_from_options(options)
        self._warm = False  # the first inference prints a native log line too
        self.select = select
        self.crop_scale = float(crop_scale)
        self.search_tiles = search_tiles
        self._previous: np.ndarray | None = None  # x0, y0, x1, y1 of the last face found

    def __enter__(self) -> Landmarker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Release MediaPipe's graph."""
        self._task.close()

    def reset(self) -> None:
        """Forget the previous face (the next frame is searched from the whole frame)."""
        self._previous = None

    def detect(self, rgb: np.ndarray) -> MeshFrame:
        """The face mesh of one frame.

        Parameters
        ----------
        rgb
            ``(H, W, 3)`` uint8 RGB image.

        Returns
        -------
        MeshFrame
            Invalid (NaN points, identity matrix) when no face is found.
        """
        rgb = np.asarray(rgb)
        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {rgb.shape} {rgb.dtype}")
        height, width = rgb.shape[:2]
        whole = np.array([0, 0, width, height])
        searches: list[list[np.ndarray]] = []
        if self._previous is not None and self.crop_scale > 0:
            crop = crop_around(self._previous, scale=self.crop_scale, size=(width, height))
            if crop[2] < width or crop[3] < height:
                searches.append([crop])
        searches.append([whole])
        if self.search_tiles:
            searches.append(tiles((width, height)))
        for regions in searches:
            faces = self._merge([face for region in regions for face in self._faces(rgb, region)])
            if faces:
                best = self._choose(faces, (width, height), previous=self._previous)
                self._previous = _box(best.xy)
                return MeshFrame(best.xy, best.z, True, best.blendshapes, best.matrix, len(faces), best.region)
        self._previous = None
        return MeshFrame(
            np.full((N_MESH, 2), np.nan),
            np.full(N_MESH, np.nan),
            False,
            np.zeros(len(BLENDSHAPE_NAMES), np.float32),
            np.eye(4),
            0,
            whole,
        )

    def _faces(self, rgb: np.ndarray, region: np.ndarray) -> list[MeshFrame]:
        """Every face MediaPipe finds in ``region`` (``x0, y0, w, h``), in frame pixels."""
        import mediapipe as mp

        x0, y0, w, h = (int(v) for v in region)
        crop = np.ascontiguousarray(rgb[y0 : y0 + h, x0 : x0 + w])
        with native_logs_silenced() if not self._warm else contextlib.nullcontext():
            result = self._task.detect(mp.Image(image_format=mp.ImageFormat.SRGB, data=crop))
        self._warm = True
        faces = []
        for k, landmarks in enumerate(result.face_landmarks):
            norm = np.array([(p.x, p.y, p.z) for p in landmarks], dtype=np.float64)
            if norm.shape != (N_MESH, 3):
                raise RuntimeError(f"face landmarker returned {norm.shape[0]} landmarks, expected {N_MESH}")
            xy = norm[:, :2] * (w, h) + (x0, y0)
            scores = np.zeros(len(BLENDSHAPE_NAMES), np.float32)
            for c in result.face_blendshapes[k]:
                scores[c.index] = c.score
            matrix = np.asarray(result.facial_transformation_matrixes[k], dtype=np.float64).reshape(4, 4)
            faces.append(MeshFrame(xy, norm[:, 2] * w, True, scores, matrix, 1, region.copy()))
        return faces

    @staticmethod
    def _merge(faces: list[MeshFrame]) -> list[MeshFrame]:
        """Drop faces found again in an overlapping tile (boxes overlapping by half or more)."""
        kept: list[MeshFrame] = []
        for face in faces:
            if all(_overlap(_box(face.xy), _box(k.xy)) < 0.5 for k in kept):
                kept.append(face)
        return kept

    def _choose(self, faces: list[MeshFrame], size: tuple[int, int], *, previous: np.ndarray | None) -> MeshFrame:
        """The face to keep: the one overlapping the ``previous`` frame's face box (``x0, y0, x1,
        y1``) most, so that a face once chosen is followed while another in the searched region
        grows or comes nearer the centre; the :attr:`select` rule when there is no previous face
        or none of the faces overlaps it (a cut, or the face came back elsewhere)."""
        boxes = [_box(f.xy) for f in faces]
        if previous is not None:
            overlap = [_overlap(previous, b) for b in boxes]
            if max(overlap) > 0:
                return faces[int(np.argmax(overlap))]
        if self.select == "largest":
            score = [-(b[2] - b[0]) * (b[3] - b[1]) for b in boxes]
        else:
            centre = (np.asarray(size) - 1) / 2
            score = [float(np.hypot(*((b[:2] + b[2:]) / 2 - centre))) for b in boxes]
        return faces[int(np.argmin(score))]
