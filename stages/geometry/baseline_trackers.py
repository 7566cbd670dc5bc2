"""Baseline trackers a benchmark compares the NCC tracker with: pyramidal Lucas-Kanade with a
forward-backward check (:class:`LKTracker`) and OpenCV's correlation-filter trackers, one per
point (:class:`OpenCVTracker`: CSRT, KCF, MOSSE)."""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from stages.geometry.correlation import inside, intensity


class LKTracker:
    """Pyramidal Lucas-Kanade (``cv2.calcOpticalFlowPyrLK``) with a forward-backward check (as in
    OpenCV's ``samples/python/lk_track.py``): a point is valid when both passes converge, the
    round trip returns within ``fb_px`` of the start and the point lies in the frame."""

    def __init__(self, *, template_px: int = 15, levels: int = 2, fb_px: float = 1.0) -> None:
        import cv2

        self.params = dict(
            winSize=(template_px, template_px),
            maxLevel=levels,
            criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01),
        )
        self.fb_px = fb_px

    @staticmethod
    def _gray8(frame: np.ndarray) -> np.ndarray:
        return np.clip(np.rint(intensity(frame)), 0, 255).astype(np.uint8)

    def start(self, frame: np.ndarray, xy: np.ndarray) -> None:
        self.previous = self._gray8(frame)
        self.last = xy.astype(np.float64).copy()

    def step(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        import cv2

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


def _cv2() -> Any:
    """OpenCV, imported when first used (importing it costs start-up time)."""
    import cv2

    return cv2


class OpenCVTracker:
    """One OpenCV single-object tracker (CSRT, KCF or legacy MOSSE) per point, on a
    ``box_px``-square box centred on the point; the point is the box centre plus the first
    frame's sub-pixel offset. ``valid`` is the tracker's success flag and the point in frame."""

    FACTORIES: dict[str, Callable[[], Any]] = {
        "csrt": lambda: _cv2().TrackerCSRT_create(),
        "kcf": lambda: _cv2().TrackerKCF_create(),
        "mosse": lambda: _cv2().legacy.TrackerMOSSE_create(),
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
