"""Benchmark area ``seen``: the performer's expressions as a viewer sees them on the result.

``bench.py real`` judges the target's *geometry* (the run's ``data.npz``) against the performer's
landmarks. A viewer sees the *image*: a frown whose brows the warp barely moves, or an "O" the
examples cannot show, is missing however well the points follow. Here the same face landmarker
reads both videos, the performer's clip and the run's ``video/result.mp4`` (head motion and all,
as a user gets it), and its blendshape scores (MediaPipe's 52 ARKit categories, 0..1, trained to
be read on any face) are compared per state (:data:`SEEN_STATES`, each pooling the named
categories, left and right of the subject):

- ``seen_<state>_r_<stem>_onto_<target>``: Pearson r of the performer's and the result's scores
  over the frames where both show a face;
- ``seen_<state>_peak_ratio_<stem>_onto_<target>``: over the performer's peak frames (score at
  least :data:`PEAK`), the result's mean score above its own median over the clip, over the
  performer's mean above the performer's median (1: the result shows the state as strongly; 0:
  not at all); no row where the performer has fewer than :data:`MIN_FRAMES` peak frames;
- ``seen_face_found_frac_<stem>_onto_<target>``: frames of the result where the landmarker finds
  a face.

Every dev clip is mapped onto actor packs built by ``pack_build.yaml`` from two dev clips
(:data:`scripts.bench_real.PACK_CLIPS`, never a clip onto its own pack). Aggregates over all runs:
``seen_<state>_peak_ratio_min`` / ``_median`` and ``seen_<state>_r_median``.

    python scripts/bench.py seen [--json] [--clip PATH ...] [--pack-from PATH ...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from scripts.bench_real import DEV_CLIPS, PACK_CLIPS, build_pack, read_frames, run_pipeline
from scripts.real_states import MIN_FRAMES, pearson, unit_of
from stages.landmarks.landmarker import BLENDSHAPE_NAMES, Landmarker

BENCH = "seen"
PEAK = 0.5  # a blendshape score at least this is the state shown (MediaPipe's scores are 0..1)
#: state -> the blendshape categories pooled for it (subject's Left and Right where there are two)
SEEN_STATES: dict[str, tuple[str, ...]] = {
    "eyes_shut": ("eyeBlinkLeft", "eyeBlinkRight"),
    "brow_down": ("browDownLeft", "browDownRight"),
    "brow_inner_up": ("browInnerUp",),
    "jaw_open": ("jawOpen",),
    "pucker": ("mouthPucker",),
    "funnel": ("mouthFunnel",),
    "smile": ("mouthSmileLeft", "mouthSmileRight"),
    "lip_press": ("mouthPressLeft", "mouthPressRight"),
}


def row(metric: str, value: float, unit: str) -> dict[str, Any]:
    return {"bench": BENCH, "metric": metric, "value": float(value), "unit": unit}


def blendshape_scores(frames: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The landmarker's blendshape scores ``(T, 52)`` (:data:`BLENDSHAPE_NAMES` order) and face
    found ``(T,)`` of ``frames``."""
    with Landmarker() as landmarker:
        meshes = [landmarker.detect(rgb) for rgb in frames]
    return np.stack([m.blendshapes for m in meshes]), np.array([m.valid for m in meshes])


def seen_measures(performer: np.ndarray, result: np.ndarray, valid: np.ndarray) -> dict[str, float]:
    """The ``r``, ``peak_ratio`` and ``peak_frames`` of every :data:`SEEN_STATES` state (module
    docstring), keyed ``<state>_<measure>``.

    Parameters
    ----------
    performer, result : (T, 52) float
        Blendshape scores per frame of the performer's clip and of the result video.
    valid : (T,) bool
        Frames where both show a face.
    """
    valid = np.asarray(valid, bool)
    performer = np.asarray(performer, np.float64)[valid]
    result = np.asarray(result, np.float64)[valid]
    out: dict[str, float] = {}
    for state, categories in SEEN_STATES.items():
        columns = [BLENDSHAPE_NAMES.index(c) for c in categories]
        p, t = performer[:, columns], result[:, columns]
        peak = (p >= PEAK).ravel()
        out[f"{state}_r"] = pearson(p.ravel(), t.ravel())
        out[f"{state}_peak_frames"] = float(peak.sum())
        if peak.sum() >= MIN_FRAMES:
            rise_p = (p - np.median(p, axis=0)).ravel()[peak]
            rise_t = (t - np.median(t, axis=0)).ravel()[peak]
            out[f"{state}_peak_ratio"] = float(rise_t.mean() / rise_p.mean())
        else:
            out[f"{state}_peak_ratio"] = float("nan")
    return out


def aggregate(measured: Mapping[str, Mapping[str, float]]) -> list[dict[str, Any]]:
    """``seen_<state>_peak_ratio_min`` / ``_median`` and ``seen_<state>_r_median`` over the runs
    ``{run name: seen_measures}`` (NaN left out; no row where no run defines it)."""
    rows = []
    for state in SEEN_STATES:
        for key, reducers in ((f"{state}_peak_ratio", ("min", "median")), (f"{state}_r", ("median",))):
            values = [m[key] for m in measured.values() if np.isfinite(m.get(key, np.nan))]
            if not values:
                continue
            for how in reducers:
                rows.append(row(f"seen_{key}_{how}", float(getattr(np, how)(values)), unit_of(key)))
    return rows


def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(prog="bench.py seen")
    parser.add_argument("--clip", action="append", type=Path, default=[], help="a real clip (repeatable)")
    parser.add_argument(
        "--pack-from",
        action="append",
        type=Path,
        default=[],
        help=f"map onto a pack built from this clip (repeatable; default: the dev clips {', '.join(PACK_CLIPS)})",
    )
    options = parser.parse_args(args.extra)
    clips = options.clip or (sorted(DEV_CLIPS.glob("*.mp4")) if DEV_CLIPS.is_dir() else [])
    if not clips:
        raise SystemExit(f"bench.py seen: no clips (pass --clip, or put the dev clips in {DEV_CLIPS})")
    work = Path(args.work) / BENCH
    cache = work / "cache"
    pack_clips = options.pack_from or [DEV_CLIPS / name for name in PACK_CLIPS]
    targets = {clip.stem: build_pack(clip, work, cache) for clip in pack_clips}
    rows: list[dict[str, Any]] = []
    measured: dict[str, dict[str, float]] = {}
    for clip in clips:
        performer, found_p = blendshape_scores(read_frames(clip))
        for name, pack in targets.items():
            if name == clip.stem:
                continue
            folder = work / "runs" / clip.stem / name
            run_pipeline(clip, folder, "--input", f"target={pack}", cache=cache)
            result, found_r = blendshape_scores(read_frames(folder / "out" / "video" / "result.mp4"))
            label = f"{clip.stem}_onto_{name}"
            measured[label] = seen_measures(performer, result, found_p & found_r)
            rows.append(row(f"seen_face_found_frac_{label}", found_r.mean(), "fraction"))
            rows += [
                row(f"seen_{key}_{label}", value, unit_of(key)) for key, value in measured[label].items() if np.isfinite(value)
            ]
            print(f"bench seen: {label}", flush=True, file=sys.stderr)
    return rows + aggregate(measured)
