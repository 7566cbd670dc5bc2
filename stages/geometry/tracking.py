"""Tracking points through a clip frame by frame with one of the trackers (paper Sec. 14.1):
``ncc`` (:class:`stages.geometry.ncc_tracker.NCCTracker`, the default), ``csrt``, ``kcf``,
``mosse`` or ``lk`` (:mod:`stages.geometry.baseline_trackers`). Frames are consumed one at a time
from an iterable; a clip is never held in memory."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np

from stages.geometry.baseline_trackers import LKTracker, OpenCVTracker
from stages.geometry.face_model import FaceModel
from stages.geometry.ncc_tracker import NCCTracker
from stages.geometry.tracker_options import DEFAULTS, TrackerOptions

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
        In [0, 1]: NCC of the patch found with its template (``ncc``), forward-backward
        agreement ``exp(-e / fb_px)`` (``lk``), 1 or 0 as reported by the OpenCV tracker
        (``csrt``, ``kcf``, ``mosse``).
    """

    xy: np.ndarray
    valid: np.ndarray
    confidence: np.ndarray


def make_tracker(method: str, options: TrackerOptions = DEFAULTS, *, face_model: FaceModel | None = None):
    """The tracker object for ``method`` (one of :data:`METHODS`), configured from the options
    that apply to it (``template_px`` sets the LK window and, with ``search_px``, the box of the
    OpenCV trackers); ``face_model`` is for ``ncc`` only."""
    if method == "ncc":
        return NCCTracker(options, face_model=face_model)
    if method == "lk":
        return LKTracker(template_px=options.template_px, fb_px=options.fb_px)
    if method in OpenCVTracker.FACTORIES:
        return OpenCVTracker(method, box_px=options.template_px + 2 * options.search_px)
    raise ValueError(f"unknown tracking method {method!r}; expected one of {METHODS}")


def track_points(
    frames: Iterable[np.ndarray],
    init_xy: np.ndarray,
    *,
    method: str = "ncc",
    options: TrackerOptions = DEFAULTS,
    face_model: FaceModel | None = None,
    progress: Callable[[int], None] = lambda n: None,
) -> Tracks:
    """Track N points through a clip, frame by frame.

    Parameters
    ----------
    frames : iterable of (H, W, 3) RGB or (H, W) gray images
        The clip in order, consumed one frame at a time.
    init_xy : (N, 2) float
        Positions in the first frame, px.
    method : str
        ``ncc`` (default), ``csrt``, ``kcf``, ``mosse`` or ``lk``.
    options, face_model
        Passed to :func:`make_tracker`.
    progress : callable
        Called with 1 after each frame.

    Returns
    -------
    Tracks
        ``xy (T, N, 2)``, ``valid (T, N)``, ``confidence (T, N)``; frame 0 is ``init_xy``, valid.

    Raises
    ------
    ValueError
        An unknown ``method``, or a clip without frames.
    """
    init_xy = np.asarray(init_xy, dtype=np.float64)
    tracker = make_tracker(method, options, face_model=face_model)
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
        raise ValueError("expected a clip with frames, got none")
    return Tracks(np.stack(xy), np.stack(valid), np.stack(confidence).astype(np.float32))
