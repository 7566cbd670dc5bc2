"""``preview.side_by_side``: performer | result frames at a common height, for a quick-look video.

The output is an 8-bit sRGB ``frames`` stream with even width and height (what H.264 in yuv420p
needs); ``write.video`` encodes it. By default it is half the result's height: a review copy
beside the master EXR frames, and a quarter of the pixels to encode (docs/writers.md measures
the encoder at both sizes). The stage is not cached: a resize and a concatenation cost
less than writing, hashing and reading back its frames (1.2 GB for 300 frames at 800x1666), so
its chunks are computed while the encoder reads them.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from runner.stage import Context, FrameStage, Param, StageError, StreamInfo
from stages.color import to_uint8


def _even(x: float) -> int:
    """Nearest even integer >= 2."""
    return max(2, 2 * round(x / 2))


def _even_down(x: int) -> int:
    """Largest even integer <= x, at least 2."""
    return max(2, x - x % 2)


def side_by_side_size(performer_hw: tuple[int, int], result_hw: tuple[int, int], *, height: int = 0) -> tuple[int, int, int]:
    """Layout of the preview: ``(height, performer_width, result_width)`` in px, all even.

    Parameters
    ----------
    performer_hw, result_hw : (H, W) of the two inputs.
    height : common height; 0 = the result's height. Rounded down to even; each panel keeps
        its aspect ratio, its width rounded to the nearest even number.
    """
    common = _even_down(height or result_hw[0])
    widths = [_even(w * common / h) for h, w in (performer_hw, result_hw)]
    return common, widths[0], widths[1]


def _fit(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """Resize (H, W, 3) uint8 to (height, width, 3): area averaging to half the height or less
    (every source pixel counted), bilinear above (a milder shrink, or an enlargement, where
    bilinear skips no source pixel; OpenCV's area averaging costs 5 times more at a
    non-integer factor: 640x480 -> 534x400, the demo's performer)."""
    import cv2

    if image.shape[:2] == (height, width):
        return image
    area = 2 * height <= image.shape[0]
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA if area else cv2.INTER_LINEAR)


def side_by_side(performer: np.ndarray, result: np.ndarray, *, height: int = 0) -> np.ndarray:
    """Put two frames side by side (performer left, result right) at a common height.

    Parameters
    ----------
    performer : (H1, W1, 3) uint8, or float sRGB in [0, 1]
    result : (H2, W2, 3) uint8, or float sRGB in [0, 1]
    height : common height in px; 0 = the result's height (rounded down to even).

    Returns
    -------
    (H, W1' + W2', 3) uint8 sRGB with H, W1', W2' even (see :func:`side_by_side_size`).
    """
    h, w_left, w_right = side_by_side_size(performer.shape[:2], result.shape[:2], height=height)
    left = _fit(np.ascontiguousarray(to_uint8(performer)), h, w_left)
    right = _fit(np.ascontiguousarray(to_uint8(result)), h, w_right)
    return np.concatenate([left, right], axis=1)


class SideBySide(FrameStage):
    """Performer | result, uint8 RGB at a common even height, for ``write.video``."""

    name = "preview.side_by_side"
    version = "3"
    doc = "performer | result frames side by side (uint8 RGB, even size) for a preview video"
    inputs = {"performer": "frames", "result": "frames"}
    outputs = {"frames": "frames"}
    cached = False  # cheaper to recompute than to store and read back (see the module's docstring)
    params = (
        Param("height", int, 0, "common height in px (rounded down to even); 0 = scale x the result's height", min=0, max=8192),
        Param("scale", float, 0.5, "common height as a fraction of the result's height, when height is 0", min=0.05, max=1.0),
    )

    @staticmethod
    def _height(result_height: int, params: Mapping[str, Any]) -> int:
        """The common height in px: ``height``, else ``scale`` x the result's (at least 2)."""
        return params["height"] or max(2, round(params["scale"] * result_height))

    def stream_info(self, inputs: Mapping[str, Any], params: Mapping[str, Any]) -> StreamInfo:
        performer, result = inputs["performer"].info, inputs["result"].info
        if performer.frames != result.frames:
            raise StageError(f"preview.side_by_side: 'performer' has {performer.frames} frames, 'result' {result.frames}")
        h, w_left, w_right = side_by_side_size(
            (performer.height, performer.width),
            (result.height, result.width),
            height=self._height(result.height, params),
        )
        return StreamInfo(frames=result.frames, fps=result.fps, width=w_left + w_right, height=h)

    def process(
        self, start: int, stop: int, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context
    ) -> dict[str, Any]:
        self.stream_info(inputs, params)
        performer = inputs["performer"].read(start, stop)
        result = inputs["result"].read(start, stop)
        for port, frames in (("performer", performer), ("result", result)):
            if frames.ndim != 4 or frames.shape[3] != 3:
                raise StageError(f"preview.side_by_side: input '{port}' must be RGB (B, H, W, 3), got {frames.shape}")
        height = self._height(result.shape[1], params)
        pairs = [side_by_side(p, r, height=height) for p, r in zip(performer, result)]
        return {"frames": np.stack(pairs)}
