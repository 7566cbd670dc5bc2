"""The report's contact sheet: performer | result at chosen frames, as JPEG bytes.

Only the chosen frames are read from the two frame streams (``read(i, i + 1)``), so the sheet
costs a handful of frames however long the clip is.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from runner.stage import FrameStream
from stages.writers.preview import side_by_side

JPEG_QUALITY = 85


def sheet_frames(frames: int, *, evenly: int, peaks: Sequence[tuple[int, str]]) -> list[tuple[int, str]]:
    """The frames of the contact sheet: ``evenly`` frames evenly spaced over the clip (first and
    last included) and the expression peaks, sorted, one entry per frame.

    Parameters
    ----------
    frames : frame count T of the clip.
    evenly : how many evenly spaced frames (0: none).
    peaks : ``[(frame, label)]`` from :func:`stages.report.series.peak_frames`.

    Returns
    -------
    ``[(frame, label)]``; evenly spaced frames are labelled ``""`` unless they are also a peak.
    """
    if frames < 1 or evenly < 0:
        raise ValueError(f"expected frames >= 1 and evenly >= 0, got frames={frames}, evenly={evenly}")
    labels = {int(f): "" for f in np.unique(np.round(np.linspace(0, frames - 1, evenly)).astype(int))}
    labels.update({int(f): label for f, label in peaks if 0 <= f < frames})
    return sorted(labels.items())


def sheet_image(performer: FrameStream, result: FrameStream, frame: int, *, height: int) -> bytes:
    """Performer | result of one frame at a common ``height`` (px), as JPEG bytes.

    The performer stream holds uint8 RGB ``(H, W, 3)``, the result float sRGB in [0, 1] or uint8;
    :func:`stages.writers.preview.side_by_side` puts them at the same height.
    """
    pair = side_by_side(performer.read(frame, frame + 1)[0, ..., :3], result.read(frame, frame + 1)[0, ..., :3],
                        height=height)
    ok, jpeg = cv2.imencode(".jpg", cv2.cvtColor(pair, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise ValueError(f"could not encode the contact-sheet image of frame {frame} as JPEG")
    return jpeg.tobytes()
