"""Feature point tracking in a performer clip (paper Sec. 14.1: "correlation-based tracking").

The default tracker (``method="ncc"``) follows each point of the tracked subset with normalized
cross-correlation (NCC) of a small template inside a search window centred on a constant-velocity
prediction, refines the correlation peak to sub-pixel precision with a parabola fitted through the
peak and its neighbours, scores every point in every frame (peak NCC value and peak-to-sidelobe
ratio), and controls drift by matching the first-frame template (the anchor) in the same window:
where the anchor matches well, its position wins and the running template is re-anchored there.
A point that is lost or leaves the frame is flagged invalid, carried along by the similarity motion
of the valid points, and keeps being searched for; it is never dropped.

``method`` also selects OpenCV's correlation-filter trackers (``csrt``, ``kcf``, ``mosse``, one
tracker per point on a box around it) and pyramidal Lucas-Kanade with a forward-backward check
(``lk``), so that a benchmark can compare them on the same clip.

Frames are consumed one at a time from an iterable; a clip is never held in memory.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping

import cv2
import numpy as np

from runner.stage import Context, Param, SequenceStage, StageError
from stages.geometry.compensate import apply_similarity, fit_similarity
from stages.layout import load_layout

METHODS = ("ncc", "csrt", "kcf", "mosse", "lk")


@dataclass
class Tracks:
    """Tracked trajectories of N points over T frames.

    Attributes
    ----------
    xy : (T, N, 2) float64
        Positions in px (x right, y down, origin at the centre of the top-left pixel). For an
        invalid entry, the tracker's best guess (``ncc``: the last valid position carried along
        with the valid points; other methods: the last valid position).
    valid : (T, N) bool
        True where the tracker is confident the point was found inside the frame.
    confidence : (T, N) float32
        In [0, 1]: peak NCC score (``ncc``), forward-backward agreement ``exp(-e / fb_px)``
        (``lk``), 1 or 0 as reported by the OpenCV tracker (``csrt``, ``kcf``, ``mosse``).
    """

    xy: np.ndarray
    valid: np.ndarray
    confidence: np.ndarray


def to_gray(frame: np.ndarray) -> np.ndarray:
    """An ``(H, W)``, ``(H, W, 1)`` or RGB ``(H, W, 3)`` frame as an ``(H, W)`` float32 image in
    the frame's own intensity units."""
    if frame.ndim == 3 and frame.shape[2] == 3:
        frame = cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2GRAY)
    elif frame.ndim == 3:
        frame = frame[..., 0]
    return np.asarray(frame, dtype=np.float32)


def inside(xy: np.ndarray, width: int, height: int) -> np.ndarray:
    """``(..., 2)`` positions -> ``(...)`` bool, True for positions on the image ``[0, W-1] x [0, H-1]``."""
    return (xy[..., 0] >= 0) & (xy[..., 0] <= width - 1) & (xy[..., 1] >= 0) & (xy[..., 1] <= height - 1)


def correlation_peaks(response: np.ndarray, *, exclude: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel peaks, peak values and peak-to-sidelobe ratios of a stack of correlation surfaces.

    Parameters
    ----------
    response : (N, S, S) float
        Correlation surfaces (e.g. ``cv2.TM_CCOEFF_NORMED`` outputs); cell ``(j, i)`` is the score
        of a displacement ``(i - (S-1)/2, j - (S-1)/2)`` px from the window centre.
    exclude : int
        Half-size of the square around the peak left out of the sidelobe (MOSSE's PSR).

    Returns
    -------
    offset : (N, 2) float64
        Peak displacement ``(dx, dy)`` in px from the window centre; the sub-pixel part comes from
        a parabola through the peak and its two neighbours along each axis (zero on the border).
    peak : (N,) float64
        Peak value.
    psr : (N,) float64
        ``(peak - mean(sidelobe)) / std(sidelobe)``.
    """
    n, s, _ = response.shape
    flat = response.reshape(n, s * s).astype(np.float64)
    arg = flat.argmax(axis=1)
    py, px = np.divmod(arg, s)
    rows = np.arange(n)
    peak = flat[rows, arg]

    def parabola(minus: np.ndarray, plus: np.ndarray, at_edge: np.ndarray) -> np.ndarray:
        curvature = minus - 2.0 * peak + plus
        ok = (~at_edge) & (curvature < 0)
        shift = np.where(ok, 0.5 * (minus - plus) / np.where(ok, curvature, -1.0), 0.0)
        return np.clip(shift, -0.5, 0.5)

    surface = response.astype(np.float64)
    edge_x = (px == 0) | (px == s - 1)
    edge_y = (py == 0) | (py == s - 1)
    sub_x = parabola(surface[rows, py, np.maximum(px - 1, 0)], surface[rows, py, np.minimum(px + 1, s - 1)], edge_x)
    sub_y = parabola(surface[rows, np.maximum(py - 1, 0), px], surface[rows, np.minimum(py + 1, s - 1), px], edge_y)
    centre = (s - 1) / 2.0
    offset = np.stack([px - centre + sub_x, py - centre + sub_y], axis=1)

    grid = np.arange(s)
    near = (np.abs(grid[None, :, None] - py[:, None, None]) <= exclude) & (
        np.abs(grid[None, None, :] - px[:, None, None]) <= exclude
    )
    side = ~near.reshape(n, s * s)
    count = side.sum(axis=1)
    mean = (flat * side).sum(axis=1) / count
    var = (((flat - mean[:, None]) ** 2) * side).sum(axis=1) / count
    psr = (peak - mean) / (np.sqrt(var) + 1e-6)
    return offset, peak, psr


def carry_along(last: np.ndarray, found: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """New positions ``(N, 2)``: ``found`` where ``valid``; elsewhere ``last`` moved by the 2D
    similarity (eq. 8-9) that best maps the valid points' ``last`` onto their ``found`` (the head's
    motion), by their translation if only one is valid, not at all if none is."""
    if valid.sum() >= 2:
        moved = apply_similarity(fit_similarity(last[valid], found[valid]), last)
    elif valid.any():
        moved = last + (found[valid] - last[valid])
    else:
        moved = last
    return np.where(valid[:, None], found, moved)


class NCCTracker:
    """Normalized cross-correlation tracker with a constant-velocity prediction and an anchor.

    Per point and frame: a ``template_px`` square template is correlated
    (``cv2.TM_CCOEFF_NORMED``, on luma, or on RGB with ``color``) with a window of side
    ``template_px + 2 * search_px`` centred on the predicted position (rounded to a pixel), once
    with the running template (the last valid appearance) and once with the first-frame template
    (the anchor). The anchor's peak is used when its score reaches ``anchor_score``, which
    re-anchors a drifting running template; else the running template's peak.

    A point is valid when the chosen score reaches ``min_score``, its peak-to-sidelobe ratio
    reaches ``min_psr``, the patch found has a standard deviation of at least ``min_contrast``
    (an occluder or a flat region is not a match) and its template lies wholly in the frame (a
    point closer than half a template to the border is flagged). The running template is
    refreshed at valid points only. An invalid point is carried along with the valid points
    (:func:`carry_along`), which is also its predicted velocity, so it is found again when it
    reappears.
    """

    def __init__(
        self,
        *,
        template_px: int = 15,
        search_px: int = 8,
        min_score: float = 0.7,
        min_psr: float = 0.0,
        anchor_score: float = 0.9,
        min_contrast: float = 2.0,
        color: bool = False,
    ) -> None:
        self.color = color
        self.min_contrast = min_contrast
        self.size = (template_px, template_px)
        self.window = (template_px + 2 * search_px, template_px + 2 * search_px)
        self.min_score = min_score
        self.min_psr = min_psr
        self.anchor_score = anchor_score

    def start(self, frame: np.ndarray, xy: np.ndarray) -> None:
        image = self.image(frame)
        self.height, self.width = image.shape[:2]
        self.anchor = [cv2.getRectSubPix(image, self.size, (float(x), float(y))) for x, y in xy]
        self.template = list(self.anchor)
        self.last = xy.astype(np.float64).copy()
        self.velocity = np.zeros_like(self.last)

    def image(self, frame: np.ndarray) -> np.ndarray:
        """The frame as matched: ``(H, W)`` gray or ``(H, W, 3)`` colour, float32."""
        return np.ascontiguousarray(frame, dtype=np.float32) if self.color and frame.ndim == 3 else to_gray(frame)

    def step(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        image = self.image(frame)
        centre = np.rint(self.last + self.velocity)
        n = len(centre)
        s = self.window[0] - self.size[0] + 1
        running = np.empty((n, s, s), np.float32)
        anchored = np.empty((n, s, s), np.float32)
        for i, (cx, cy) in enumerate(centre):
            window = cv2.getRectSubPix(image, self.window, (float(cx), float(cy)))
            running[i] = cv2.matchTemplate(window, self.template[i], cv2.TM_CCOEFF_NORMED)
            anchored[i] = cv2.matchTemplate(window, self.anchor[i], cv2.TM_CCOEFF_NORMED)
        off_run, score_run, psr_run = correlation_peaks(running)
        off_anc, score_anc, psr_anc = correlation_peaks(anchored)
        use_anchor = score_anc >= self.anchor_score
        found = centre + np.where(use_anchor[:, None], off_anc, off_run)
        score = np.where(use_anchor, score_anc, score_run)
        psr = np.where(use_anchor, psr_anc, psr_run)
        half = self.size[0] // 2
        in_frame = inside(found - half, self.width - 2 * half, self.height - 2 * half)
        patches = [cv2.getRectSubPix(image, self.size, (float(x), float(y))) for x, y in found]
        contrast = np.array([patch.std() for patch in patches])
        valid = (score >= self.min_score) & (psr >= self.min_psr) & (contrast >= self.min_contrast) & in_frame
        for i in np.flatnonzero(valid):
            self.template[i] = patches[i]
        carried = carry_along(self.last, found, valid)
        self.velocity = carried - self.last
        self.last = carried
        return self.last.copy(), valid, np.clip(score, 0.0, 1.0)


class LKTracker:
    """Pyramidal Lucas-Kanade (``cv2.calcOpticalFlowPyrLK``) with a forward-backward check (as in
    OpenCV's ``samples/python/lk_track.py``): a point is valid when both passes converge, the
    round trip returns within ``fb_px`` of the start and the point lies in the frame."""

    def __init__(self, *, template_px: int = 15, levels: int = 2, fb_px: float = 1.0) -> None:
        self.params = dict(
            winSize=(template_px, template_px),
            maxLevel=levels,
            criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01),
        )
        self.fb_px = fb_px

    @staticmethod
    def _gray8(frame: np.ndarray) -> np.ndarray:
        return np.clip(np.rint(to_gray(frame)), 0, 255).astype(np.uint8)

    def start(self, frame: np.ndarray, xy: np.ndarray) -> None:
        self.previous = self._gray8(frame)
        self.last = xy.astype(np.float64).copy()

    def step(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        gray = self._gray8(frame)
        p0 = self.last.astype(np.float32).reshape(-1, 1, 2)
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(self.previous, gray, p0, None, **self.params)
        p0r, st0, _ = cv2.calcOpticalFlowPyrLK(gray, self.previous, p1, None, **self.params)
        p1 = p1.reshape(-1, 2).astype(np.float64)
        error = np.linalg.norm(p0r.reshape(-1, 2) - self.last, axis=1)
        valid = (st1.ravel() == 1) & (st0.ravel() == 1) & (error <= self.fb_px)
        valid &= inside(p1, gray.shape[1], gray.shape[0])
        self.last = np.where(valid[:, None], p1, self.last)
        self.previous = gray
        return self.last.copy(), valid, np.exp(-error / self.fb_px).astype(np.float32)


class OpenCVTracker:
    """One OpenCV single-object tracker (CSRT, KCF or legacy MOSSE) per point, on a
    ``box_px``-square box centred on the point; the point is the box centre plus the first
    frame's sub-pixel offset. ``valid`` is the tracker's success flag and the point in frame."""

    FACTORIES: dict[str, Callable[[], Any]] = {
        "csrt": lambda: cv2.TrackerCSRT_create(),
        "kcf": lambda: cv2.TrackerKCF_create(),
        "mosse": lambda: cv2.legacy.TrackerMOSSE_create(),
    }

    def __init__(self, method: str, *, box_px: int = 31) -> None:
        self.factory = self.FACTORIES[method]
        self.half = box_px // 2

    @staticmethod
    def rgb(frame: np.ndarray) -> np.ndarray:
        """The frame as a contiguous 3-channel image (gray frames repeated)."""
        gray = frame.ndim == 2 or frame.shape[2] == 1
        return np.ascontiguousarray(np.repeat(frame.reshape(frame.shape[:2] + (1,)), 3, axis=2) if gray else frame)

    def start(self, frame: np.ndarray, xy: np.ndarray) -> None:
        image = self.rgb(frame)
        self.height, self.width = image.shape[:2]
        corner = np.rint(xy) - self.half
        self.offset = xy - np.rint(xy)
        self.trackers = []
        side = 2 * self.half + 1
        for cx, cy in corner:
            tracker = self.factory()
            tracker.init(image, (int(cx), int(cy), side, side))
            self.trackers.append(tracker)
        self.last = xy.astype(np.float64).copy()

    def step(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        image = self.rgb(frame)
        valid = np.zeros(len(self.trackers), bool)
        found = self.last.copy()
        for i, tracker in enumerate(self.trackers):
            ok, box = tracker.update(image)
            if ok:
                found[i] = (box[0] + (box[2] - 1) / 2.0, box[1] + (box[3] - 1) / 2.0) + self.offset[i]
                valid[i] = True
        valid &= inside(found, self.width, self.height)
        self.last = np.where(valid[:, None], found, self.last)
        return self.last.copy(), valid, valid.astype(np.float32)


def make_tracker(method: str, *, template_px: int = 15, search_px: int = 8, min_score: float = 0.7,
                 min_psr: float = 0.0, anchor_score: float = 0.9, min_contrast: float = 2.0, color: bool = False,
                 fb_px: float = 1.0):
    """The tracker object for ``method`` (one of :data:`METHODS`), configured from the options
    that apply to it (``template_px`` sets the LK window and, with ``search_px``, the box of the
    OpenCV trackers)."""
    if method == "ncc":
        return NCCTracker(template_px=template_px, search_px=search_px, min_score=min_score,
                          min_psr=min_psr, anchor_score=anchor_score, min_contrast=min_contrast, color=color)
    if method == "lk":
        return LKTracker(template_px=template_px, fb_px=fb_px)
    if method in OpenCVTracker.FACTORIES:
        return OpenCVTracker(method, box_px=template_px + 2 * search_px)
    raise ValueError(f"unknown tracking method {method!r}; expected one of {METHODS}")


def track_points(frames: Iterable[np.ndarray], init_xy: np.ndarray, *, method: str = "ncc",
                 progress: Callable[[int], None] = lambda n: None, **options: Any) -> Tracks:
    """Track N points through a clip, frame by frame.

    Parameters
    ----------
    frames : iterable of (H, W, 3) RGB or (H, W) gray images
        The clip in order, consumed one frame at a time.
    init_xy : (N, 2) float
        Positions in the first frame, px.
    method : str
        ``ncc`` (default), ``csrt``, ``kcf``, ``mosse`` or ``lk``.
    progress : callable
        Called with 1 after each frame.
    **options
        Passed to :func:`make_tracker`.

    Returns
    -------
    Tracks
        ``xy (T, N, 2)``, ``valid (T, N)``, ``confidence (T, N)``; frame 0 is ``init_xy``, valid.
    """
    init_xy = np.asarray(init_xy, dtype=np.float64)
    tracker = make_tracker(method, **options)
    xy, valid, confidence = [], [], []
    for t, frame in enumerate(frames):
        if t == 0:
            tracker.start(frame, init_xy)
            found, ok, score = init_xy.copy(), np.ones(len(init_xy), bool), np.ones(len(init_xy), np.float32)
        else:
            found, ok, score = tracker.step(frame)
        xy.append(found)
        valid.append(ok)
        confidence.append(score)
        progress(1)
    if not xy:
        raise StageError("track: the input clip has no frames")
    return Tracks(np.stack(xy), np.stack(valid), np.stack(confidence).astype(np.float32))


def read_first_frame_points(path: Path) -> tuple[list[str], np.ndarray]:
    """Read named first-frame positions from a ``.csv`` (header ``name,x,y``) or ``.json`` file
    (``{"names": [...], "xy": [[x, y], ...]}`` or ``{name: [x, y], ...}``, optionally under a
    ``"points"`` key). Returns the names and an ``(N, 2)`` float64 array in px."""
    path = Path(path)
    if not path.is_file():
        raise StageError(f"first-frame points file not found: {path}")
    try:
        if path.suffix.lower() == ".csv":
            with path.open(newline="") as handle:
                rows = list(csv.DictReader(handle))
            names = [row["name"] for row in rows]
            xy = np.array([[float(row["x"]), float(row["y"])] for row in rows], dtype=np.float64)
        elif path.suffix.lower() == ".json":
            data = json.loads(path.read_text())
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
    return [str(n) for n in names], xy


def order_by_layout(path: Path, names: list[str], xy: np.ndarray, expected: tuple[str, ...],
                    size: tuple[int, int]) -> np.ndarray:
    """Check first-frame points against the layout's tracked subset and the frame size; return
    them ``(N, 2)`` in the layout's order. ``size`` is ``(W, H)``."""
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


def first_frame_file(init: Path, name: str) -> Path:
    """The first-frame points file: ``init`` itself if it is a file, else ``init / name``, else
    (``name`` empty) the only ``*_track0.csv`` in the folder ``init``."""
    if not init.is_dir():
        return init
    if name:
        return init / name
    candidates = sorted(init.glob("*_track0.csv"))
    if len(candidates) != 1:
        raise StageError(f"{init}: found {len(candidates)} first-frame points files *_track0.csv "
                         f"({', '.join(c.name for c in candidates[:4])}); set the parameter init_file")
    return candidates[0]


def iter_frames(stream: Any) -> Iterator[np.ndarray]:
    """Frames of a :class:`runner.stage.FrameStream`, one at a time, read chunk by chunk."""
    for _, chunk in stream.chunks():
        yield from chunk


class CorrelationTrack(SequenceStage):
    """``track.correlation``: the tracked subset of the layout through the performer clip.

    ``init`` is the folder holding the first-frame positions of the tracked points
    (``init_file`` in it; a path to the file itself is accepted too), read by
    :func:`read_first_frame_points` and checked against the layout's tracked subset and the
    frame size.
    """

    name = "track.correlation"
    version = "1"
    doc = "track the layout's tracked subset through a clip (NCC, or CSRT/KCF/MOSSE/LK)"
    inputs = {"frames": "frames", "init": "dir"}
    outputs = {"points": "points"}
    params = (
        Param("layout", str, "zhang134", "layout name or YAML path; its `tracked` subset is followed"),
        Param("init_file", str, "", "first-frame points file (name,x,y CSV or JSON) in the init folder; "
              "empty: the folder's only *_track0.csv"),
        Param("method", str, "ncc", "tracker", choices=METHODS),
        Param("template_px", int, 15, "template side in px (LK window; OpenCV trackers' box is template+2*search)"),
        Param("search_px", int, 8, "search radius in px around the constant-velocity prediction"),
        Param("min_score", float, 0.7, "ncc: lowest peak NCC of a valid point"),
        Param("min_psr", float, 0.0, "ncc: lowest peak-to-sidelobe ratio of a valid point (0 = off: NCC peaks "
              "on smooth skin are broad, so their PSR is low even when right)"),
        Param("min_contrast", float, 2.0, "ncc: lowest standard deviation (intensity levels) of a valid point's patch"),
        Param("anchor_score", float, 0.9, "ncc: first-frame template score above which it re-anchors the point"),
        Param("color", bool, False, "ncc: correlate RGB instead of luma (about 3x slower)"),
        Param("fb_px", float, 1.0, "lk: largest forward-backward error of a valid point, px"),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        params = {p.name: p.default for p in self.params} | dict(params)
        stream = inputs["frames"]
        info = stream.info
        layout = load_layout(params["layout"])
        expected = tuple(layout.point_names[i] for i in layout.tracked)
        path = first_frame_file(Path(inputs["init"]), params["init_file"])
        names, xy = read_first_frame_points(path)
        init = order_by_layout(path, names, xy, expected, (info.width, info.height))
        options = {p.name: params[p.name] for p in self.params
                   if p.name not in ("layout", "init_file", "method")}
        tracks = track_points(iter_frames(stream), init, method=params["method"],
                              progress=ctx.progress, **options)
        return {
            "points": {
                "xy": tracks.xy,
                "valid": tracks.valid,
                "confidence": tracks.confidence,
                "names": np.array(expected),
                "fps": np.array(info.fps, dtype=np.float64),
                "size": np.array([info.width, info.height], dtype=np.int64),
            }
        }
