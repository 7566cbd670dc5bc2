"""The report's contact sheet: performer | result at chosen frames, as JPEG bytes in a bundle.

The frames are chosen from the run's geometry alone (evenly spaced, plus the expression peaks of
:func:`stages.report.series.peak_frames`), so :class:`stages.report.stage.ContactSheet` knows them
before the result is synthesized and picks them from the frame streams as those are computed:
only the chosen frames are read, in ascending order (``read(i, i + 1)``), so a run hands them
over as they pass and a cached run synthesizes just those frames again.

The ``sheet`` bundle: ``frame (K,) int64`` and ``label (K,) str`` (the chosen frames and their
peak labels, ``""`` for an evenly spaced one), ``jpeg (N,) uint8`` (the K JPEGs one after the
other) and ``jpeg_end (K,) int64`` (where each ends), ``frames ()`` (the clip's frame count T),
``fps ()``, ``performer_size (2,)`` and ``result_size (2,)`` (``[W, H]`` of the two streams).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import cv2
import numpy as np

from stages.report import series
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


def chosen_frames(
    tracked: Mapping[str, np.ndarray], target: Mapping[str, np.ndarray], *, reference: int, frames: int, evenly: int
) -> list[tuple[int, str]]:
    """:func:`sheet_frames` with the reference frame (labelled ``reference``) and the peaks of the
    performer's (else the target's) expression signals relative to it; evenly spaced frames and
    the reference only when the geometries have no expression signal
    (:func:`stages.report.series.expression_series` refuses them)."""
    try:
        peaks = series.peak_frames(series.expression_series(tracked, target, reference=reference))
    except ValueError:
        peaks = []
    peaks = [(f, label) for f, label in peaks if f != reference] + [(reference, "reference")]
    return sheet_frames(frames, evenly=evenly, peaks=peaks)


def sheet_jpeg(performer: np.ndarray, result: np.ndarray, *, height: int) -> bytes:
    """Performer | result of one frame at a common ``height`` (px), as JPEG bytes.

    Parameters
    ----------
    performer : (H1, W1, C >= 3) uint8 RGB (channels past the third are ignored).
    result : (H2, W2, C >= 3) float sRGB in [0, 1] or uint8;
        :func:`stages.writers.preview.side_by_side` puts the two at the same height.
    """
    pair = side_by_side(performer[..., :3], result[..., :3], height=height)
    ok, jpeg = cv2.imencode(".jpg", cv2.cvtColor(pair, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise ValueError("could not encode a contact-sheet image as JPEG")
    return jpeg.tobytes()


def sheet_bundle(
    chosen: Sequence[tuple[int, str]],
    jpegs: Sequence[bytes],
    *,
    frames: int,
    fps: float,
    performer_size: tuple[int, int],
    result_size: tuple[int, int],
) -> dict[str, np.ndarray]:
    """The ``sheet`` bundle (module docstring) of the ``chosen`` frames and their ``jpegs``
    (same order); sizes are ``(W, H)``."""
    if len(chosen) != len(jpegs):
        raise ValueError(f"expected one JPEG per chosen frame, got {len(jpegs)} for {len(chosen)}")
    return {
        "frame": np.array([f for f, _ in chosen], np.int64),
        "label": np.array([label for _, label in chosen], dtype=str),
        "jpeg": np.frombuffer(b"".join(jpegs), np.uint8),
        "jpeg_end": np.cumsum([len(j) for j in jpegs], dtype=np.int64),
        "frames": np.array(frames, np.int64),
        "fps": np.array(fps, np.float64),
        "performer_size": np.array(performer_size, np.int64),
        "result_size": np.array(result_size, np.int64),
    }


def sheet_images(sheet: Mapping[str, np.ndarray]) -> list[tuple[int, str, bytes]]:
    """``[(frame, label, jpeg)]`` of a ``sheet`` bundle, in its order. Raises ValueError for a
    bundle whose fields disagree."""
    frame, label, end = (np.asarray(sheet[k]) for k in ("frame", "label", "jpeg_end"))
    data = np.asarray(sheet["jpeg"], np.uint8).tobytes()
    if not (len(frame) == len(label) == len(end)) or (len(end) and (np.any(np.diff(end) < 0) or end[-1] != len(data))):
        raise ValueError(
            f"sheet: {len(frame)} frames, {len(label)} labels and {len(end)} JPEG ends over {len(data)} bytes do not agree"
        )
    starts = np.concatenate([[0], end[:-1]]).astype(int)
    return [(int(f), str(lab), data[a : int(b)]) for f, lab, a, b in zip(frame, label, starts, end)]
