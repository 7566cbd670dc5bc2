"""A synthetic hand pasted over a clip's face, with the truth of which face regions it hides.

    python scripts/occluder.py --clip CLIP [--clip CLIP ...] [--work DIR] [--no-half] [--json]

The hand is drawn, not photographed: a palm and five fingers (capsules) whose rounded cross
sections are shaded by one light, with a drop shadow on the face, a mottled skin texture and a
soft edge. Its colour is the performer's own skin (measured on the clean clip's cheeks and
forehead) or another skin tone. Over each event's frames it follows the face (the clean clip's
points) and moves a little about it (a few percent of the eye distance, a few degrees).

Truth (:func:`coverage`): a region (``stages.occlusion.regions``) is *covered* in a frame when
the hand's opacity exceeds 0.5 over more than half of the region's outline polygon, drawn at
the clean clip's points of that frame.

The benchmark (:func:`occlusion_rows`, rows of ``bench.py real``): the clean clip and its
variant with the hand over the mouth for 30 frames from the first frame (a clip that starts
occluded; the performer's own skin tone) and over one eye (the one seen larger) for 30 frames
in the middle (another skin tone) are each run through ``landmarks.mediapipe``,
``landmarks.layout`` and ``occlusion.detect``; so is a second variant with the same hands over
the mouth for the first half of the clip and over the eye for the second half
(``real_occlusion_half_*`` rows, as the variant's). Rows, per clip (``_<stem>``):
``real_occlusion_recall`` / ``real_occlusion_precision`` over frames x regions of the variant
(a covered frame where the landmarker finds no face counts as missed), ``real_occlusion_recall_<region>``
per region the hand covers, ``real_occlusion_noface_frac`` (the covered frames x regions where the
landmarker found no face), ``real_occlusion_false_frac`` (flagged frames x regions over judged
frames x regions of the clean clip, where every flag is false) and
``real_occlusion_false_frac_<region>``; over the clips: ``real_occlusion_recall_min``,
``real_occlusion_precision_min``, ``real_occlusion_half_recall_min``,
``real_occlusion_half_precision_min``, ``real_occlusion_false_frac_max`` (:func:`aggregate_rows`).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from stages.occlusion.regions import REGION_OUTLINES, REGIONS  # noqa: E402

BENCH = "real"
EVENT_FRAMES = 30

#: Other skin tones (sRGB), light to dark: a hand of another person.
TONES = np.array([[236, 200, 176], [214, 160, 120], [170, 112, 78], [112, 70, 48]], np.float64)

#: Layout points whose neighbourhood gives the performer's skin colour.
SKIN_POINTS = ("cheek_l", "cheek_r", "forehead_c")


@dataclass(frozen=True)
class Event:
    """The hand over ``region`` (``mouth``, ``eye_l``, ``eye_r``) in frames ``[start, stop)``,
    coloured ``colour`` (sRGB, 3 floats)."""

    region: str
    start: int
    stop: int
    colour: tuple[float, float, float]


# --- the hand ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Hand:
    """A hand drawn on a square canvas, fingers up, palm centre at the canvas centre.

    ``alpha (S, S)`` opacity in [0, 1]; ``shade (S, S)`` linear-light multiplier of the skin
    colour (shading and texture); ``palm_px``: the palm's width on the canvas, px.
    """

    alpha: np.ndarray
    shade: np.ndarray
    palm_px: float


def _capsule(x: np.ndarray, y: np.ndarray, a: np.ndarray, b: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """A round capsule from ``a`` to ``b`` (canvas px): its height (0..1, the cross section of a
    cylinder of ``radius``, 0 outside) and the position along it (0 at ``a``, 1 at ``b``)."""
    ab = b - a
    u = np.clip(((x - a[0]) * ab[0] + (y - a[1]) * ab[1]) / float(ab @ ab), 0.0, 1.0)
    d = np.hypot(x - a[0] - u * ab[0], y - a[1] - u * ab[1]) / radius
    return np.sqrt(np.clip(1.0 - d * d, 0.0, None)), u


def make_hand(side: int = 256, *, seed: int = 0) -> Hand:
    """Draw the back of a hand: a palm (an ellipsoid), four fingers and a thumb (capsules), lit
    from the upper left (Lambert on the height field's normals), with knuckle creases across
    each digit, nails at the tips and two scales of mottling.

    Each part's height is a round cross section; the hand's height is their maximum, so the
    valleys between touching fingers shade darker, as the gaps between fingers do.
    """
    import cv2

    rng = np.random.default_rng(seed)
    palm = side * 0.3
    y, x = np.mgrid[0:side, 0:side].astype(np.float64)
    cx = cy = (side - 1) / 2
    u, v = (x - cx) / palm, (y - cy) / palm  # palm widths, v down
    height = np.sqrt(np.clip(1.0 - (u / 0.5) ** 2 - (v / 0.58) ** 2, 0.0, None))
    digits = []  # (base, tip, radius) canvas px
    for base_u, angle, length in [(-0.36, -6.0, 0.80), (-0.12, -2.0, 0.92), (0.12, 2.0, 0.87), (0.35, 7.0, 0.68)]:
        angle = np.radians(angle + rng.uniform(-2.0, 2.0))
        a = np.array([cx + base_u * palm, cy - 0.4 * palm])
        digits.append((a, a + length * palm * np.array([np.sin(angle), -np.cos(angle)]), 0.12 * palm))
    a = np.array([cx + 0.38 * palm, cy + 0.15 * palm])
    digits.append((a, a + 0.6 * palm * np.array([np.sin(np.radians(55.0)), -np.cos(np.radians(55.0))]), 0.14 * palm))
    marks = np.ones_like(height)  # creases darker, nails lighter
    for a, b, radius in digits:
        h, along = _capsule(x, y, a, b, radius)
        own = h > height
        crease = sum(np.exp(-0.5 * ((along - c) * float(np.hypot(*(b - a))) / (0.02 * palm)) ** 2) for c in (0.36, 0.63))
        nail = (along > 0.8) & (h > 0.55)
        marks = np.where(own, (1.0 - 0.2 * crease) * np.where(nail, 1.2, 1.0), marks)
        height = np.maximum(height, h)
    gy, gx = np.gradient(height * 0.35 * palm)
    normal = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    light = np.array([-0.45, -0.55, 0.70])
    light /= np.linalg.norm(light)
    lambert = np.clip(normal @ light, 0.0, None)
    coarse = cv2.GaussianBlur(rng.standard_normal((side, side)), (0, 0), side / 40)
    fine = cv2.GaussianBlur(rng.standard_normal((side, side)), (0, 0), 1.5)
    texture = 1.0 + 0.06 * coarse / max(coarse.std(), 1e-9) + 0.012 * fine / max(fine.std(), 1e-9)
    shade = (0.25 + 0.85 * lambert) * (0.75 + 0.25 * np.sqrt(height)) * cv2.GaussianBlur(marks, (0, 0), 0.6) * texture
    alpha = cv2.GaussianBlur(np.clip(height * 8.0, 0.0, 1.0), (0, 0), 0.7)
    return Hand(alpha=alpha.astype(np.float32), shade=shade.astype(np.float32), palm_px=palm)


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    c = np.asarray(c, np.float64) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _linear_to_srgb(c: np.ndarray) -> np.ndarray:
    c = np.clip(c, 0.0, 1.0)
    return 255.0 * np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)


def hand_transform(hand: Hand, centre: np.ndarray, palm_px: float, angle_deg: float, *, mirror: bool = False) -> np.ndarray:
    """The 2 x 3 affine map from the hand's canvas to the frame: palm centre to ``centre`` (px),
    palm ``palm_px`` wide, turned ``angle_deg`` clockwise on screen (0: fingers up, thumb to the
    right; ``mirror``: thumb to the left, the other hand)."""
    side = hand.alpha.shape[0]
    scale = palm_px / hand.palm_px
    theta = np.radians(angle_deg)
    rot = scale * np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    if mirror:
        rot = rot @ np.diag([-1.0, 1.0])
    c = (side - 1) / 2
    return np.hstack([rot, (np.asarray(centre, np.float64) - rot @ [c, c])[:, None]])


def paste_hand(frame: np.ndarray, hand: Hand, transform: np.ndarray, colour: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Composite the hand over ``frame`` ``(H, W, 3)`` uint8 sRGB with its drop shadow, in linear
    light; returns the new frame and the hand's opacity ``(H, W)`` float32 in the frame."""
    import cv2

    h, w = frame.shape[:2]
    alpha = cv2.warpAffine(hand.alpha, transform, (w, h), flags=cv2.INTER_LINEAR, borderValue=0.0)
    shade = cv2.warpAffine(hand.shade, transform, (w, h), flags=cv2.INTER_LINEAR, borderValue=0.0)
    palm = hand.palm_px * float(np.hypot(*transform[:, 0]))
    offset = np.float64([[1, 0, 0.06 * palm], [0, 1, 0.09 * palm]])
    shadow = cv2.GaussianBlur(cv2.warpAffine(alpha, offset, (w, h), borderValue=0.0), (0, 0), 0.08 * palm)
    face = _srgb_to_linear(frame) * (1.0 - 0.45 * shadow)[..., None]
    skin = _srgb_to_linear(colour)[None, None, :] * shade[..., None]
    out = face * (1.0 - alpha[..., None]) + skin * alpha[..., None]
    return np.round(_linear_to_srgb(out)).astype(np.uint8), alpha


# --- where the hand goes -------------------------------------------------------------------------


def _columns(names: list[str], wanted: tuple[str, ...] | list[str]) -> list[int]:
    return [names.index(n) for n in wanted]


def eye_axis(xy: np.ndarray, names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Per frame: the eye distance (px, outer corners) ``(T,)`` and the eye line's angle (deg,
    clockwise on screen) ``(T,)``."""
    left, right = (xy[:, c] for c in _columns(names, ("eye_l_6", "eye_r_6")))
    d = right - left
    return np.hypot(d[:, 0], d[:, 1]), np.degrees(np.arctan2(d[:, 1], d[:, 0]))


def hand_pose(event: Event, t: int, xy: np.ndarray, names: list[str]) -> tuple[np.ndarray, float, float, bool]:
    """Palm centre (px), palm width (px), angle (deg) and mirroring (:func:`hand_transform`) of
    the hand of ``event`` in frame ``t`` from the clean points ``xy (N, 2)``.

    Over the mouth: sideways (fingers towards the image's right, thumb down), palm 1.05 eye
    distances wide, centred 0.15 eye distances above the lips' centre, so that it hides the
    mouth and the lower nose. Over an eye: fingers up, tilted 25 degrees inwards, thumb
    outwards, palm 0.85 eye distances wide, centred 0.2 eye distances outwards of the eye's
    centre, so that it hides the eye and its brow and not the other eye. A slow drift of 5 % of
    the eye distance and 4 degrees moves it a little.
    """
    eye, roll = (a[0] for a in eye_axis(xy[None], names))
    along = np.array([np.cos(np.radians(roll)), np.sin(np.radians(roll))])
    down = np.array([-along[1], along[0]])
    phase = 2 * np.pi * (t - event.start)
    drift = 0.05 * eye * (np.sin(phase / 37 + 0.3) * along + np.sin(phase / 53 + 1.1) * down)
    wobble = 4.0 * np.sin(phase / 45)
    if event.region == "mouth":
        centre = xy[[names.index(f"mouth_outer_{k}") for k in range(16)]].mean(axis=0) - 0.15 * eye * down
        return centre + drift, 1.05 * eye, roll + 90.0 + wobble, False
    left = event.region == "eye_l"
    centre = xy[[names.index(f"{event.region}_{k}") for k in range(12)]].mean(axis=0)
    outwards = -along if left else along
    return (
        centre + 0.2 * eye * outwards - 0.05 * eye * down + drift,
        0.85 * eye,
        roll + (25.0 if left else -25.0) + wobble,
        left,
    )


def region_polygons(xy: np.ndarray, names: list[str]) -> dict[str, np.ndarray]:
    """Each region's outline polygon ``(P, 2)`` px at one frame's points ``xy (N, 2)``
    (:data:`stages.occlusion.regions.REGION_OUTLINES` of the zhang134 layout)."""
    from stages.layout import load_layout

    layout = load_layout("zhang134")
    out = {}
    for region in REGIONS:
        polygon = [layout.point_names[i] for i in layout.subregion(REGION_OUTLINES[region]).polygon]
        out[region] = xy[_columns(names, polygon)]
    return out


def coverage(alpha: np.ndarray, xy: np.ndarray, names: list[str]) -> np.ndarray:
    """The fraction of each region's outline (its polygon's pixels, outline included, so that a
    shut eye's collapsed polygon still has pixels) where the hand's opacity exceeds 0.5.

    Parameters
    ----------
    alpha : (H, W) float, the hand's opacity in the frame.
    xy : (N, 2) float px, the clean clip's points of that frame.

    Returns
    -------
    (R,) float in [0, 1], over :data:`REGIONS`; NaN for a region entirely outside the frame.
    """
    import cv2

    h, w = alpha.shape
    out = np.full(len(REGIONS), np.nan)
    for r, polygon in enumerate(region_polygons(xy, names).values()):
        x0, y0 = np.floor(polygon.min(axis=0)).astype(int) - 1
        x1, y1 = np.ceil(polygon.max(axis=0)).astype(int) + 2
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
        if x1 <= x0 or y1 <= y0:
            continue
        mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
        shifted = np.round((polygon - [x0, y0]) * 16).astype(np.int32)
        cv2.fillPoly(mask, [shifted], 1, shift=4)
        cv2.polylines(mask, [shifted], True, 1, thickness=1, shift=4)
        inside = mask.astype(bool)
        out[r] = float((alpha[y0:y1, x0:x1][inside] > 0.5).mean()) if inside.any() else np.nan
    return out


def skin_colour(
    frames: Iterator[tuple[int, np.ndarray]], xy: np.ndarray, names: list[str], valid: np.ndarray, *, samples: int = 12
) -> np.ndarray:
    """The performer's skin colour (sRGB, 3 floats): the median over ``samples`` frames spread
    over the clip of the pixels within 0.06 eye distances of :data:`SKIN_POINTS`."""
    eye, _ = eye_axis(xy, names)
    picks = set(np.flatnonzero(valid)[np.linspace(0, valid.sum() - 1, samples).round().astype(int)].tolist())
    columns = _columns(names, SKIN_POINTS)
    pixels = []
    for start, chunk in frames:
        for k, frame in enumerate(chunk):
            t = start + k
            if t not in picks:
                continue
            r = max(2, int(0.06 * eye[t]))
            for x, y in np.round(xy[t, columns]).astype(int):
                patch = frame[max(y - r, 0) : y + r + 1, max(x - r, 0) : x + r + 1]
                pixels.append(patch.reshape(-1, 3))
    return np.median(np.concatenate(pixels), axis=0)


def other_tone(skin: np.ndarray) -> np.ndarray:
    """The tone of :data:`TONES` farthest in luminance from ``skin`` (sRGB)."""
    luma = np.array([0.299, 0.587, 0.114])
    return TONES[int(np.argmax(np.abs(TONES @ luma - skin @ luma)))]


def default_events(
    xy: np.ndarray, names: list[str], valid: np.ndarray, skin: np.ndarray, *, frames: int = EVENT_FRAMES
) -> list[Event]:
    """The benchmark's two events of ``frames`` frames each: the mouth from the first frame
    (the performer's own skin), then the eye seen larger (its outline's mean area over the clip)
    in the frames around the middle of the clip (another tone)."""
    total = len(xy)
    if total < 2 * frames + 10:
        raise ValueError(f"clip too short for {frames}-frame occluder events: {total} frames, need {2 * frames + 10}")
    polygons = [region_polygons(xy[t], names) for t in np.flatnonzero(valid)]
    area = {side: np.mean([_area(p[f"eye_{side}"]) for p in polygons]) for side in "lr"}
    eye = "eye_l" if area["l"] >= area["r"] else "eye_r"
    start = max(total // 2 - frames // 2, frames + 5)
    return [
        Event("mouth", 0, frames, tuple(float(c) for c in skin)),
        Event(eye, start, start + frames, tuple(float(c) for c in other_tone(skin))),
    ]


def _area(polygon: np.ndarray) -> float:
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * abs(float(x @ np.roll(y, -1) - y @ np.roll(x, -1)))


def occlude(
    frames: Iterator[tuple[int, np.ndarray]], xy: np.ndarray, names: list[str], events: list[Event], *, seed: int = 0
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Paste the hand of each event over its frames.

    Parameters
    ----------
    frames : the clean clip's ``(start, chunk (B, H, W, 3) uint8)`` in order.
    xy : (T, N, 2) float px, the clean clip's points (they place the hand and outline the regions).
    events : the hands; at most one per frame.

    Yields
    ------
    Per frame: the frame ``(H, W, 3)`` uint8 and the coverage of each region ``(R,)``
    (:func:`coverage`; 0 where no hand).
    """
    hand = make_hand(seed=seed)
    for start, chunk in frames:
        for k, frame in enumerate(chunk):
            t = start + k
            event = next((e for e in events if e.start <= t < e.stop), None)
            if event is None or not np.isfinite(xy[t]).all():
                yield frame, np.zeros(len(REGIONS))
                continue
            centre, palm, angle, mirror = hand_pose(event, t, xy[t], names)
            transform = hand_transform(hand, centre, palm, angle, mirror=mirror)
            pasted, alpha = paste_hand(frame, hand, transform, np.array(event.colour))
            yield pasted, np.nan_to_num(coverage(alpha, xy[t], names))


def write_variant(clip: Path, out: Path, xy: np.ndarray, names: list[str], events: list[Event]) -> np.ndarray:
    """Write ``out`` (H.264, crf 12, the clip's rate; no audio) with the hands of ``events``
    pasted over ``clip``; return the coverage ``(T, R)``."""
    from stages.video import VideoWriter, probe

    info = probe(clip)
    fractions = []
    with VideoWriter(out, fps=info.fps, width=info.width, height=info.height, crf=12) as writer:
        for frame, fraction in occlude(clip_stream(clip).chunks(), xy, names, events):
            writer.write(frame[None])
            fractions.append(fraction)
    return np.array(fractions)


# --- running the detector ------------------------------------------------------------------------


def clip_stream(clip: Path) -> Any:
    """The clip's frames as a :class:`runner.stage.FrameStream`, decoded chunk by chunk
    (``video.decode``), never held whole."""
    from runner.stage import Context
    from runner.streams import ComputedStream, chunk_ranges
    from stages.video import VideoDecode, probe

    info = probe(clip)
    ranges = chunk_ranges(info.frames, 16)
    decode, ctx = VideoDecode(), Context(device="cpu", files_dir=lambda port: Path("/nonexistent"))
    return ComputedStream(info, ranges, lambda i: decode.process(*ranges[i], {"video": clip}, {}, ctx)["frames"])


def detect(clip: Path, cache: Path | None = None) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """``landmarks.mediapipe`` -> ``landmarks.layout`` -> ``occlusion.detect`` on ``clip`` through
    the stage API; returns the ``points`` and ``occlusion`` bundles. With ``cache`` (an ``.npz``
    path) the points are kept there and read back on the next call."""
    from runner.stage import Context
    from stages.landmarks.stage import FaceLandmarks, LayoutPoints
    from stages.occlusion.stage import DetectOcclusion

    ctx = Context(device="cpu", files_dir=lambda port: Path("/nonexistent"), log=logging.getLogger("occluder"))
    if cache is not None and cache.exists():
        with np.load(cache, allow_pickle=False) as kept:
            points = {k: kept[k] for k in kept.files}
    else:
        marks = FaceLandmarks().run({"frames": clip_stream(clip)}, {}, ctx)["landmarks"]
        points = LayoutPoints().run({"landmarks": marks}, {}, ctx)["points"]
        if cache is not None:
            cache.parent.mkdir(parents=True, exist_ok=True)
            np.savez(cache, **points)
    occlusion = DetectOcclusion().run({"frames": clip_stream(clip), "points": points}, {}, ctx)["occlusion"]
    return points, occlusion


# --- rows ----------------------------------------------------------------------------------------


def row(metric: str, value: float, unit: str) -> dict[str, Any]:
    return {"bench": BENCH, "metric": metric, "value": float(value), "unit": unit}


def recall_precision(flagged: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Recall and precision of ``flagged`` against ``truth`` (bool arrays of one shape); NaN
    where there is nothing to count."""
    hits = float((flagged & truth).sum())
    return (hits / truth.sum() if truth.any() else np.nan, hits / flagged.sum() if flagged.any() else np.nan)


def half_events(events: list[Event], frames: int) -> list[Event]:
    """The half-clip variant of the benchmark's ``events``: the same hands, the mouth's over the
    first half of the clip's ``frames``, the eye's over the second half."""
    mouth, eye = events
    return [Event("mouth", 0, frames // 2, mouth.colour), Event(eye.region, frames // 2, frames, eye.colour)]


def variant_rows(
    clip: Path, work: Path, name: str, prefix: str, events: list[Event], xy: np.ndarray, names: list[str]
) -> list[dict[str, Any]]:
    """Paste the hands of ``events`` over ``clip`` (``work/<name>.mp4``, truth in
    ``work/<name>_truth.npz``), run the detector on it and score it against the truth:
    ``<prefix>_recall``, ``_precision``, ``_noface_frac`` and ``_recall_<region>``, each suffixed
    ``_<clip file stem>``."""
    stem = clip.stem
    variant = work / f"{name}.mp4"
    fraction = write_variant(clip, variant, xy, names, events)
    truth = fraction > 0.5
    np.savez(
        work / f"{name}_truth.npz",
        regions=np.array(REGIONS),
        covered=truth,
        fraction=fraction.astype(np.float32),
        events=np.array([[e.start, e.stop] for e in events]),
        event_regions=np.array([e.region for e in events]),
        colours=np.array([e.colour for e in events]),
    )
    _, found = detect(variant)
    recall, precision = recall_precision(found["occluded"], truth)
    rows = [
        row(f"{prefix}_recall_{stem}", recall, "fraction"),
        row(f"{prefix}_precision_{stem}", precision, "fraction"),
        row(f"{prefix}_noface_frac_{stem}", (truth & ~found["valid"][:, None]).sum() / max(truth.sum(), 1), "fraction"),
    ]
    return rows + [
        row(f"{prefix}_recall_{region}_{stem}", recall_precision(found["occluded"][:, r], truth[:, r])[0], "fraction")
        for r, region in enumerate(REGIONS)
        if truth[:, r].any()
    ]


def occlusion_rows(clip: Path, work: Path, *, event_frames: int = EVENT_FRAMES, half: bool = True) -> list[dict[str, Any]]:
    """The occlusion rows of one clip (module doc): the false alarms on the clean clip, the
    variant with the hand over each region for ``event_frames`` (``real_occlusion_*``) and, with
    ``half``, the half-clip variant (``real_occlusion_half_*``). Files under ``work``: ``points.npz`` (the clean
    clip's points), ``occluded.mp4``, ``occluded_truth.npz``, ``half.mp4``, ``half_truth.npz``. A
    clip shorter than ``2 event_frames + 10`` frames is a ValueError."""
    stem = clip.stem
    work.mkdir(parents=True, exist_ok=True)
    points, clean = detect(clip, work / "points.npz")
    names = [str(n) for n in points["names"]]
    xy, valid = points["xy"], points["valid"].all(axis=1)
    skin = skin_colour(clip_stream(clip).chunks(), xy, names, valid)
    events = default_events(xy, names, valid, skin, frames=event_frames)
    judged = clean["valid"]
    rows = [row(f"real_occlusion_false_frac_{stem}", clean["occluded"][judged].mean(), "fraction")]
    rows += [
        row(f"real_occlusion_false_frac_{region}_{stem}", clean["occluded"][judged, r].mean(), "fraction")
        for r, region in enumerate(REGIONS)
    ]
    rows += variant_rows(clip, work, "occluded", "real_occlusion", events, xy, names)
    if half:
        rows += variant_rows(clip, work, "half", "real_occlusion_half", half_events(events, len(xy)), xy, names)
    return rows


def aggregate_rows(rows: list[dict[str, Any]], stems: list[str]) -> list[dict[str, Any]]:
    """Over the clips ``stems``: ``real_occlusion_recall_min``, ``real_occlusion_precision_min``,
    the same of the half-clip variant where its rows are there (``real_occlusion_half_*_min``)
    and ``real_occlusion_false_frac_max``."""
    value = {r["metric"]: r["value"] for r in rows}
    prefixes = ["real_occlusion"] + (["real_occlusion_half"] if f"real_occlusion_half_recall_{stems[0]}" in value else [])
    out = [
        row(f"{prefix}_{kind}_min", np.nanmin([value[f"{prefix}_{kind}_{s}"] for s in stems]), "fraction")
        for prefix in prefixes
        for kind in ("recall", "precision")
    ]  # a precision with no flag is NaN: left out
    return out + [
        row("real_occlusion_false_frac_max", np.nanmax([value[f"real_occlusion_false_frac_{s}"] for s in stems]), "fraction")
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clip", type=Path, action="append", required=True, help="a real clip (repeatable)")
    parser.add_argument("--work", type=Path, default=Path(".cache/bench/real/occlusion"), help="scratch folder")
    parser.add_argument("--json", action="store_true", help="print JSON lines only")
    parser.add_argument("--no-half", action="store_true", help="skip the half-clip variant")
    args = parser.parse_args(argv)
    from runner.stage import StageError

    rows: list[dict[str, Any]] = []
    for clip in args.clip:
        try:
            rows += occlusion_rows(clip, args.work / clip.stem, half=not args.no_half)
        except (ValueError, StageError) as exc:
            said = str(exc)
            print(f"occluder: {said}" if str(clip) in said else f"occluder: {clip}: {said}", file=sys.stderr)
            return 1
    rows += aggregate_rows(rows, [c.stem for c in args.clip])
    for r in rows:
        print(json.dumps(r) if args.json else f"{r['metric']:<52} {r['value']:.4g} {r['unit']}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
