"""Landmarks benchmark: Face Landmarker speed and the steadiness of the layout's rigid points on real clips.

``python scripts/bench_landmarks.py [--clip A.mp4 --clip B.mp4 ...]`` (or through ``scripts/bench.py``;
default: the real-texture CI clip ``fixtures/realface/astro.mp4``). Per clip (rows tagged with the clip's
file stem):

- ``fps``: frames per second of :class:`Landmarker.detect` alone (decoding not counted, wall clock), in
  the default search order (previous face's crop, whole frame, tiles), ``fps_cpu`` the same per CPU
  second of the process (all its threads; less sensitive to other jobs on the machine), and
  ``fps_whole_frame`` with the crop off;
- ``valid``: fraction of frames with a face;
- ``rigid_2d`` / ``rigid_3d``: steadiness of the layout's rigid points (hairline + inner eye corners,
  Sec. 12.1) through ``zhang134_mediapipe``: for every pair of rigid points, the standard deviation over
  the valid frames of their distance, divided by the clip's mean outer-eye-corner distance; the figure is
  the root mean square over pairs, in percent. ``_2d`` uses image distances (changed by head rotation
  too), ``_3d`` adds the mesh's relative depth z (px scale), which a rotation leaves unchanged;
- ``mouth_3d``: the same figure for the mouth corners, lip midpoints and chin, which do move with the
  expression: the rigid figure is small only if it is well below this one;
- ``truth_mean_px_<group>``, ``truth_p95_px_<group>``: for a real-texture clip with its truth beside it
  (``<stem>_truth.npz`` with the 478 landmark ``points`` and ``visible``, :mod:`lab.realface`), the mean
  and 95th percentile distance in px between the landmarker's points and the truth over the visible
  points, per point group (eyes, irises, brows, nose, lips, other, face oval) and ``all``
  (:mod:`lab.realface.evaluate`).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import av
import numpy as np

AREA = "landmarks"
DEFAULT_CLIP = Path(__file__).resolve().parent.parent / "fixtures" / "realface" / "astro.mp4"
MOUTH = ("mouth_outer_0", "mouth_outer_8", "mouth_outer_4", "mouth_outer_12", "mouth_inner_2", "mouth_inner_7", "chin")


def detect_clip(path: Path, **options: Any) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Run the landmarker over a clip: ``xyz (T, 478, 3)`` px (NaN where no face), ``valid (T,)``, and the
    wall-clock and CPU seconds spent in ``detect``."""
    from stages.landmarks.landmarker import Landmarker

    xyz, valid, seconds, cpu = [], [], 0.0, 0.0
    with Landmarker(**options) as landmarker, av.open(str(path)) as container:
        for frame in container.decode(video=0):
            rgb = frame.to_ndarray(format="rgb24")
            start, start_cpu = time.perf_counter(), time.process_time()
            mesh = landmarker.detect(rgb)
            seconds += time.perf_counter() - start
            cpu += time.process_time() - start_cpu
            xyz.append(np.column_stack([mesh.xy, mesh.z]))
            valid.append(mesh.valid)
    return np.array(xyz), np.array(valid), seconds, cpu


def pair_spread(points: np.ndarray, scale: float) -> float:
    """RMS over point pairs of the standard deviation over frames of the pair's distance, / ``scale``, in %.

    ``points (T, K, D)`` of valid frames only."""
    i, j = np.triu_indices(points.shape[1], k=1)
    distances = np.linalg.norm(points[:, i] - points[:, j], axis=-1)
    return float(100.0 * np.sqrt(np.mean(distances.std(axis=0) ** 2)) / scale)


def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    from stages.landmarks.correspondence import layout_from_mesh, load_correspondence
    from stages.layout import load_layout

    parser = argparse.ArgumentParser(prog="bench.py landmarks")
    parser.add_argument("--clip", type=Path, action="append", help=f"a video file (repeatable; default {DEFAULT_CLIP})")
    opts = parser.parse_args(getattr(args, "extra", []))
    opts.clip = opts.clip or [DEFAULT_CLIP]
    layout = load_layout("zhang134")
    correspondence = load_correspondence("zhang134_mediapipe", layout=layout)
    rows = []
    for clip in opts.clip:
        tag = clip.stem

        def row(metric: str, value: float, unit: str) -> dict[str, Any]:
            return {"bench": AREA, "metric": f"{metric}_{tag}", "value": float(value), "unit": unit}

        xyz, valid, seconds, cpu = detect_clip(clip)
        _, _, seconds_whole, _ = detect_clip(clip, crop_scale=0.0)
        rows += [
            row("fps", len(valid) / seconds, "frames/s"),
            row("fps_cpu", len(valid) / cpu, "frames/CPU s"),
            row("fps_whole_frame", len(valid) / seconds_whole, "frames/s"),
            row("valid", valid.mean(), "ratio"),
        ]
        if valid.sum() < 2:
            continue
        points = layout_from_mesh(xyz[valid], correspondence)
        eyes = layout.indices(["eye_l_6", "eye_r_6"])
        eye_distance = float(np.linalg.norm(points[:, eyes[0], :2] - points[:, eyes[1], :2], axis=-1).mean())
        rigid = list(layout.rigid)
        rows += [
            row("rigid_2d", pair_spread(points[:, rigid, :2], eye_distance), "% eye distance"),
            row("rigid_3d", pair_spread(points[:, rigid], eye_distance), "% eye distance"),
            row("mouth_3d", pair_spread(points[:, list(layout.indices(MOUTH))], eye_distance), "% eye distance"),
            row("eye_distance", eye_distance, "px"),
        ]
        rows += [row(metric, value, "px") for metric, value in truth_errors(clip).items()]
    return rows


def truth_errors(clip: Path) -> dict[str, float]:
    """``{truth_mean_px_<group>: px, truth_p95_px_<group>: px}`` against a real-texture clip's truth
    (``<stem>_truth.npz`` beside it, 478 points per frame); empty without one."""
    from lab.realface.evaluate import landmark_errors, summarize
    from stages.video import VideoDecode, probe

    truth_path = clip.with_name(f"{clip.stem}_truth.npz")
    if not truth_path.is_file():
        return {}
    with np.load(truth_path, allow_pickle=False) as truth:
        if "visible" not in truth or truth["points"].shape[1:] != (478, 2):
            return {}
        points, visible = truth["points"], truth["visible"]
    frames = VideoDecode().process(0, probe(clip).frames, {"video": str(clip)}, {}, None)["frames"]
    out = {}
    for group, (mean, p95) in summarize(landmark_errors(frames, points, visible)).items():
        out[f"truth_mean_px_{group.replace(' ', '_')}"] = mean
        out[f"truth_p95_px_{group.replace(' ', '_')}"] = p95
    return out


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    for result in run(argparse.Namespace(extra=sys.argv[1:])):
        print(json.dumps(result))
