"""Real faces: does the target follow a real performer? (`python scripts/bench.py real`)

    python scripts/bench.py real [--json] [--work DIR] [--clip PATH ...] [--realtex-frames N]
                                 [--realtex-seeds 1,2] [--no-realtex] [--no-clips]
                                 [--target PACK [--cross-sheet PNG]]

Two kinds of input:

- **Real clips** (``--clip PATH``, repeatable; default every ``*.mp4`` of ``../shared/dev-clips/``
  when that folder exists). No truth: the default ``pipeline.yaml`` is run on the clip with the
  bundled target pack, and the output target geometry (``out/data/data.npz``, ``target_xy``) is
  compared with the performer's geometry as the landmarker measured it (``tracked_xy``), through
  the expression signals of :mod:`stages.geometry.signals` (each normalized by its own outer-eye
  distance). Per clip (suffix ``_<clip file stem>``):
  ``real_mouth_follow_r`` / ``real_mouth_amp_ratio`` (inner-lip gap: Pearson r, and standard
  deviation of the target's over the performer's), ``real_brow_follow_r`` /
  ``real_brow_amp_ratio`` (brow height above the eye line), ``real_target_jitter_px`` and
  ``real_landmark_jitter_px`` (mean |second difference| over frames and points of the target
  geometry and of the performer's landmarks, px of each; ``_eye`` rows: the same over each face's
  eye distance, comparable across the two faces), ``real_image_mouth_follow_r`` /
  ``real_image_mouth_amp_ratio`` (the landmarker run on the rendered output frames, what a viewer
  sees), ``real_pose_agree_r_{yaw,pitch,roll}`` (the pipeline's head rotation relative to its
  reference frame vs the landmarker's facial transformation matrix, relative to the same frame),
  ``real_pipeline_fps`` (whole pipeline, wall, start-up included), ``real_landmarker_fps`` (the
  landmark stage alone, from the run's stage timings). Aggregates over the clips run:
  ``real_mouth_follow_r_min``, ``real_mouth_amp_ratio_min`` / ``_max``, ``real_brow_follow_r_min``,
  ``real_brow_amp_ratio_min`` / ``_max``, ``real_image_mouth_follow_r_min``. The same follow rows
  against the performer's geometry with its head rotation (since the reference frame, from the
  landmarker's own facial transformation matrix) taken out (:func:`frontal_points`):
  ``real_{mouth,brow}_{follow_r,amp_ratio}_frontal_<stem>``, aggregates
  ``real_brow_amp_ratio_frontal_min`` / ``_max``: the image-plane brow height above the eye line
  moves with head pitch, which the pipeline compensates and the target rightly does not copy; and the landmarker's
  reading of the target face itself, on the pack's annotated images against their points
  (:func:`pack_image_rows`): ``real_image_mouth_follow_r_pack``, ``real_image_mouth_amp_ratio_pack``
  (with ``--target``: ``real_cross_image_mouth_*_pack``), what the image rows are read against. A contact sheet per
  clip (performer | output at 6 frames across the clip) is written to
  ``<work>/real/<stem>/sheet.png``.
- **Real-texture clips** (``lab/realface``: the astronaut photo of scikit-image moved with
  known head pose and expression; truth exact). Per geometry method — ``landmarker`` (raw mesh
  points), ``default`` (the pipeline's smoothed points) and ``correlation`` (the paper's NCC
  tracker on the layout's tracked subset, started from the true first-frame points):
  ``real_track_err_px_<method>`` mean over all points and frames, ``..._p95``, and per point
  group (the layout's level-1 feature point sets) ``real_track_err_px_<method>_<group>``;
  ``real_track_err_px`` is the default method's mean. ``real_pose_agree_r_{yaw,pitch,roll}``:
  the pipeline's rotation relative to its reference frame vs the true one, Pearson r over
  frames; ``real_pose_err_deg``: mean absolute angle error. A contact sheet per clip goes to
  ``<work>/real/realtex_<seed>/sheet.png`` (the README's copy: these clips are public-domain
  material; frames of the dev clips are never committed).
- **Cross-identity** (``--target PACK``, issue #13): each real clip is also mapped onto another
  face's actor pack (e.g. one built by ``pack_build.yaml`` from a real-texture astronaut clip), and
  the same follow rows are reported with the prefix ``real_cross_``: ``real_cross_mouth_follow_r``,
  ``real_cross_mouth_amp_ratio``, ``real_cross_brow_follow_r``, ``real_cross_brow_amp_ratio`` per
  clip, and ``real_cross_mouth_follow_r_min`` / ``real_cross_brow_follow_r_min`` over the clips.
  ``--cross-sheet PNG`` writes a sheet that can be committed: no frame of the performer clips, only
  the performer's layout points drawn as lines on grey (:func:`points_panel`) beside the target's
  synthesized frame, six frames per clip, one row per clip.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent
DEV_CLIPS = REPO.parent / "shared" / "dev-clips"
BENCH = "real"
SHEET_FRAMES = 6
PIPELINE = REPO / "pipeline.yaml"
TARGET_PACK = REPO / "fixtures" / "packs" / "target"  # pipeline.yaml's default target
# the state rows' packs: one from a clip of many expressions, one from a talking head
PACK_CLIPS = ("LP_d18.mp4", "WDA_AlexandriaOcasioCortez_000.mp4")


def row(metric: str, value: float, unit: str) -> dict[str, Any]:
    return {"bench": BENCH, "metric": metric, "value": float(value), "unit": unit}


def run_pipeline(
    clip: Path, work: Path, *extra: str, cache: Path | None = None, pipeline: Path = PIPELINE
) -> tuple[float, dict[str, float]]:
    """Run ``pipeline`` on ``clip`` into ``work/out``, from an empty cache ``work/cache`` unless
    ``cache`` is given; return the wall time (s) and each stage's own seconds (from ``--log-json``)."""
    work.mkdir(parents=True, exist_ok=True)
    log = work / "log.jsonl"
    log.unlink(missing_ok=True)
    command = [
        sys.executable,
        "-c",
        "from runner.cli import main; main()",
        "run",
        str(pipeline),
        "--in",
        str(clip),
        "--out",
        str(work / "out"),
        "--cache-dir",
        str(cache or work / "cache"),
        "--log-json",
        str(log),
        *extra,
    ]
    start = time.perf_counter()
    result = subprocess.run(command, cwd=REPO, env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True, text=True)
    elapsed = time.perf_counter() - start
    if result.returncode != 0:
        raise SystemExit(f"pipeline failed on {clip} ({result.returncode}): {result.stderr.strip()[-2000:]}")
    seconds = {}
    for line in log.read_text().splitlines():
        event = json.loads(line)
        if event.get("event") == "stage":
            seconds[event["stage"]] = float(event.get("seconds", 0.0))
    return elapsed, seconds


def read_frames(path: Path) -> list[np.ndarray]:
    """Every frame of a video as ``(H, W, 3)`` uint8 RGB (short clips only)."""
    import av

    with av.open(str(path)) as container:
        return [frame.to_ndarray(format="rgb24") for frame in container.decode(video=0)]


def landmark_layout_points(frames: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The landmarker on ``frames``: layout points ``(T, N, 2)``, face found ``(T,)``, and the
    facial transformation matrices ``(T, 4, 4)``."""
    from stages.landmarks.correspondence import layout_from_mesh, load_correspondence
    from stages.landmarks.landmarker import Landmarker

    meshes = []
    with Landmarker() as landmarker:
        for rgb in frames:
            meshes.append(landmarker.detect(rgb))
    xy = np.stack([m.xy for m in meshes])
    return (
        layout_from_mesh(xy, load_correspondence("zhang134_mediapipe")),
        np.array([m.valid for m in meshes]),
        np.stack([m.matrix for m in meshes]),
    )


#: MediaPipe's face frame (x right, y up, z towards the camera) to the camera frame used here and
#: by OpenCV (x right, y down, z away): R_camera = FLIP R_mediapipe FLIP.
FLIP = np.diag([1.0, -1.0, -1.0])


def relative_ypr(R: np.ndarray, reference: int) -> np.ndarray:
    """``(T, 3, 3)`` rotations (camera frame) -> ``(T, 3)`` yaw, pitch, roll (deg) of
    ``R[t] R[ref]^T``."""
    from stages.geometry.rotation import ypr_yxz

    R = R / np.cbrt(np.linalg.det(R))[:, None, None]
    return ypr_yxz(R @ R[reference].T)


def frontal_points(xy: np.ndarray, z: np.ndarray, R: np.ndarray, reference: int) -> np.ndarray:
    """The performer's points with the head's rotation since frame ``reference`` taken out:
    ``(T, N, 2)`` px of ``R[ref] R[t]^T (p_t - mean_t p_t)``, ``p = (x, y, z)`` (``xy (T, N, 2)`` px,
    ``z (T, N)`` the landmarker's depth, px scale of x, away from the camera; ``R (T, 3, 3)`` the
    head rotations, camera frame). Weak perspective; a signal in eye distances needs no translation
    or scale, so none is put back."""
    p = np.concatenate([xy, z[..., None]], axis=-1)
    p = p - p.mean(axis=1, keepdims=True)
    R = R / np.cbrt(np.linalg.det(R))[:, None, None]
    return np.einsum("ij,tkj,tnk->tni", R[reference], R, p)[..., :2]


def jitter(xy: np.ndarray) -> float:
    """Mean |second difference| over frames and points, px."""
    second = xy[2:] - 2 * xy[1:-1] + xy[:-2]
    return float(np.nanmean(np.linalg.norm(second, axis=-1)))


def contact_sheet(preview: Path, path: Path, count: int = SHEET_FRAMES) -> None:
    """``count`` frames of the side-by-side preview (performer | output), evenly spaced, stacked
    in two columns, written as PNG."""
    import cv2

    frames = read_frames(preview)
    picks = [frames[i] for i in np.linspace(0, len(frames) - 1, count).round().astype(int)]
    rows = [np.concatenate(picks[k : k + 2], axis=1) for k in range(0, count, 2)]
    sheet = np.concatenate(rows, axis=0)
    cv2.imwrite(str(path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))


def follow_rows(data: Any, prefix: str, stem: str) -> list[dict[str, Any]]:
    """``<prefix>_{mouth,brow}_follow_r_<stem>`` and ``..._amp_ratio_<stem>`` of a run's data file:
    the output target geometry's expression signals against the performer's landmarks."""
    from stages.geometry.signals import expression_signals, follow

    names = [str(n) for n in data["target_names"]]
    valid = data["tracked_valid"].all(axis=1)
    performer = expression_signals(data["tracked_xy"], names)
    target = expression_signals(data["target_xy"], names)
    rows = []
    for signal, short in (("mouth_open", "mouth"), ("brow_raise", "brow")):
        r, ratio = follow(performer[signal], target[signal], valid)
        rows += [row(f"{prefix}_{short}_follow_r_{stem}", r, "r"), row(f"{prefix}_{short}_amp_ratio_{stem}", ratio, "ratio")]
    return rows


def clip_rows(clip: Path, work: Path) -> list[dict[str, Any]]:
    """The follow, jitter, pose and speed rows of one real clip."""
    from stages.geometry.signals import expression_signals, follow

    work.mkdir(parents=True, exist_ok=True)
    wall, seconds = run_pipeline(clip, work)
    data = np.load(work / "out" / "data" / "data.npz")
    names = [str(n) for n in data["target_names"]]
    performer_xy, valid = data["tracked_xy"], data["tracked_valid"].all(axis=1)
    target_xy = data["target_xy"]
    frames = len(target_xy)
    performer = expression_signals(performer_xy, names)
    target = expression_signals(target_xy, names)
    stem = clip.stem
    rows = follow_rows(data, "real", stem)
    rows += [
        row(f"real_target_jitter_px_{stem}", jitter(target_xy), "px"),
        row(f"real_landmark_jitter_px_{stem}", jitter(performer_xy[valid]), "px"),
        row(f"real_target_jitter_eye_{stem}", jitter(target_xy) / np.nanmedian(target["eye_distance_px"]), "eye"),
        row(
            f"real_landmark_jitter_eye_{stem}",
            jitter(performer_xy[valid]) / np.nanmedian(performer["eye_distance_px"][valid]),
            "eye",
        ),
    ]
    rendered, found, _ = landmark_layout_points(read_frames(work / "out" / "video" / "result.mp4"))
    seen = expression_signals(rendered, names)
    r, ratio = follow(performer["mouth_open"], seen["mouth_open"], valid & found)
    rows += [row(f"real_image_mouth_follow_r_{stem}", r, "r"), row(f"real_image_mouth_amp_ratio_{stem}", ratio, "ratio")]
    _, _, matrix = landmark_layout_points(read_frames(clip))
    reference = int(data["pose_neutral_frame"])
    head = FLIP @ matrix[:, :3, :3] @ FLIP
    frontal = expression_signals(frontal_points(performer_xy, data["tracked_z"], head, reference), names)
    for signal, short in (("mouth_open", "mouth"), ("brow_raise", "brow")):
        r, ratio = follow(frontal[signal], target[signal], valid)
        rows += [
            row(f"real_{short}_follow_r_frontal_{stem}", r, "r"),
            row(f"real_{short}_amp_ratio_frontal_{stem}", ratio, "ratio"),
        ]
    ours, theirs = relative_ypr(data["pose_R"], reference), relative_ypr(head, reference)
    for k, axis in enumerate(("yaw", "pitch", "roll")):
        r, _ = follow(theirs[:, k], ours[:, k], valid)
        rows.append(row(f"real_pose_agree_r_{axis}_{stem}", r, "r"))
    rows += [
        row(f"real_pipeline_fps_{stem}", frames / wall, "frames/s"),
        row(f"real_landmarker_fps_{stem}", frames / max(seconds.get("landmarks", np.nan), 1e-9), "frames/s"),
        row(f"real_reference_frame_{stem}", reference, "frame"),
    ]
    contact_sheet(work / "out" / "preview" / "preview.mp4", work / "sheet.png")
    return rows


def pack_image_rows(pack: Path, prefix: str) -> list[dict[str, Any]]:
    """The landmarker's own reading of a target face: run on the pack's annotated images (neutral,
    standard, examples, teeth examples), its inner-lip gap against the annotated points'.
    ``<prefix>_image_mouth_follow_r_pack`` / ``..._amp_ratio_pack``: what ``_image_`` rows of that
    target mean, as the landmarker may read this face's mouth open less (or more) than it is."""
    from stages.actor_pack import load_pack
    from stages.geometry.signals import expression_signals, follow

    target = load_pack(pack)
    expressions = [target.neutral, target.standard, *target.examples, *target.teeth_examples]
    seen, found, _ = landmark_layout_points([e.image for e in expressions])
    names = list(target.layout.point_names)
    annotated = expression_signals(np.stack([e.points for e in expressions]), names)["mouth_open"]
    r, ratio = follow(annotated, expression_signals(seen, names)["mouth_open"], found)
    return [row(f"{prefix}_image_mouth_follow_r_pack", r, "r"), row(f"{prefix}_image_mouth_amp_ratio_pack", ratio, "ratio")]


def layout_polylines(names: list[str]) -> list[tuple[np.ndarray, bool]]:
    """The layout's numbered point runs as polylines: ``(columns, closed)`` per run of names
    ``<part>_<k>`` (``k = 0, 1, ...``); eye, brow and lip outlines are closed, the rest open, and a
    point without a number is a run of one (drawn as a dot)."""
    runs: dict[str, list[tuple[int, int]]] = {}
    for column, name in enumerate(names):
        part, _, k = name.rpartition("_")
        key, order = (part, int(k)) if k.isdigit() else (name, 0)
        runs.setdefault(key, []).append((order, column))
    closed = ("eye_l", "eye_r", "brow_l", "brow_r", "mouth_outer", "mouth_inner")
    return [(np.array([c for _, c in sorted(run)]), key in closed) for key, run in runs.items()]


def points_panel(xy: np.ndarray, names: list[str], side: int, *, box: np.ndarray) -> np.ndarray:
    """The performer's layout points of one frame drawn as lines on grey: ``(side, side, 3)`` uint8
    RGB. ``box`` (``x0, y0, x1, y1`` px) is the part of the performer's frame shown, the same for
    every frame of a clip so that head motion shows; NaN points (no face) leave the panel empty."""
    import cv2

    panel = np.full((side, side, 3), 128, np.uint8)
    scale = (side - 1) / max(box[2] - box[0], box[3] - box[1])
    centre = (np.asarray(box[:2]) + box[2:]) / 2
    shift = 4  # fixed-point bits of cv2's sub-pixel drawing
    where = np.round(((xy - centre) * scale + (side - 1) / 2) * (1 << shift)).astype(np.int64) if np.isfinite(xy).all() else None
    if where is None:
        return panel
    for columns, closed in layout_polylines(names):
        if len(columns) == 1:
            cv2.circle(panel, tuple(int(v) for v in where[columns[0]]), 1 << shift, (255, 255, 255), -1, cv2.LINE_AA, shift)
        else:
            cv2.polylines(panel, [where[columns].astype(np.int32)], closed, (255, 255, 255), 1, cv2.LINE_AA, shift)
    return panel


def cross_sheet(runs: list[tuple[Any, Path]], path: Path, *, count: int = SHEET_FRAMES, side: int = 112) -> None:
    """One row per clip of ``count`` pairs (performer's layout points | the target's synthesized
    frame) at frames evenly spread over the clip, written as PNG. ``runs``: per clip its data file
    (``np.load``-ed) and result video; no performer frame is drawn, only its points."""
    import cv2

    rows = []
    for data, video in runs:
        names = [str(n) for n in data["target_names"]]
        xy = data["tracked_xy"]
        found = np.isfinite(xy).all(axis=(1, 2))
        lo, hi = np.nanmin(xy[found], axis=(0, 1)), np.nanmax(xy[found], axis=(0, 1))
        box = np.concatenate([lo, hi]) + np.array([-1, -1, 1, 1]) * 0.08 * np.max(hi - lo)
        frames = read_frames(video)
        cells = []
        for t in np.linspace(0, len(frames) - 1, count).round().astype(int):
            result = frames[t]
            height = side
            width = int(round(result.shape[1] * height / result.shape[0]))
            cells += [
                points_panel(xy[t], names, side, box=box),
                cv2.resize(result, (width, height), interpolation=cv2.INTER_AREA),
                np.full((side, 4, 3), 255, np.uint8),
            ]
        rows.append(np.concatenate(cells[:-1], axis=1))
    width = max(r.shape[1] for r in rows)
    sheet = np.concatenate([np.pad(r, ((0, 4), (0, width - r.shape[1]), (0, 0)), constant_values=255) for r in rows], axis=0)[:-4]
    jpeg = Path(path).suffix.lower() in (".jpg", ".jpeg")  # format by suffix: .png or .jpg
    cv2.imwrite(
        str(path),
        cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR),
        [cv2.IMWRITE_JPEG_QUALITY, 88] if jpeg else [cv2.IMWRITE_PNG_COMPRESSION, 9],
    )


def cross_rows(clips: list[Path], work: Path, target: Path, sheet: Path | None) -> list[dict[str, Any]]:
    """Each real clip mapped onto another face's pack ``target``: the ``real_cross_`` follow rows,
    their minima over the clips, and with ``sheet`` the points | result sheet."""
    rows, runs = [], []
    for clip in clips:
        folder = work / "cross" / clip.stem
        folder.mkdir(parents=True, exist_ok=True)
        run_pipeline(clip, folder, "--input", f"target={target}")
        data = np.load(folder / "out" / "data" / "data.npz")
        rows += follow_rows(data, "real_cross", clip.stem)
        runs.append((data, folder / "out" / "video" / "result.mp4"))
    for base in ("real_cross_mouth_follow_r", "real_cross_brow_follow_r"):
        rows.append(row(f"{base}_min", min(r["value"] for r in rows if r["metric"].startswith(base + "_")), "r"))
    rows += pack_image_rows(target, "real_cross")
    if sheet is not None:
        cross_sheet(runs, sheet)
    return rows


def aggregate(rows: list[dict[str, Any]], stems: list[str]) -> list[dict[str, Any]]:
    """The min / max rows over the clips run."""
    value = {r["metric"]: r["value"] for r in rows}
    out = []
    for base, kinds in (
        ("real_mouth_follow_r", ("min",)),
        ("real_mouth_amp_ratio", ("min", "max")),
        ("real_brow_follow_r", ("min",)),
        ("real_brow_amp_ratio", ("min", "max")),
        ("real_image_mouth_follow_r", ("min",)),
        ("real_brow_amp_ratio_frontal", ("min", "max")),
    ):
        values = [value[f"{base}_{stem}"] for stem in stems]
        for kind in kinds:
            unit = "r" if base.endswith("_r") else "ratio"
            out.append(row(f"{base}_{kind}", min(values) if kind == "min" else max(values), unit))
    return out


def realtex_rows(work: Path, frames: int, seeds: list[int]) -> list[dict[str, Any]]:
    """Geometry and pose against truth on real-texture clips (astronaut photo, known motion)."""
    from lab.realface.clip import make_clip
    from stages.geometry.signals import follow
    from stages.geometry.track import track_points
    from stages.landmarks.correspondence import layout_from_mesh, load_correspondence
    from stages.layout import load_layout

    layout = load_layout("zhang134")
    correspondence = load_correspondence("zhang134_mediapipe")
    groups = {s.name: np.array(s.points) for s in layout.feature_point_sets if s.level == 1}
    tracked = np.array(layout.tracked)
    errors: dict[str, list[np.ndarray]] = {"landmarker": [], "default": [], "correlation": [], "default_tracked": []}
    truth_ypr, ours_ypr = [], []
    for seed in seeds:
        folder = work / f"realtex_{seed}"
        clip, truth_path = make_clip(folder, frames=frames, seed=seed)
        truth = np.load(truth_path)
        true_xy = layout_from_mesh(truth["points"], correspondence)
        run_pipeline(clip, folder)
        contact_sheet(folder / "out" / "preview" / "preview.mp4", folder / "sheet.png")
        data = np.load(folder / "out" / "data" / "data.npz")
        errors["landmarker"].append(np.linalg.norm(data["tracked_xy"] - true_xy, axis=-1))
        errors["default"].append(np.linalg.norm(data["smoothed_xy"] - true_xy, axis=-1))
        errors["default_tracked"].append(errors["default"][-1][:, tracked])
        tracks = track_points(read_frames(clip), true_xy[0, tracked], method="ncc")
        errors["correlation"].append(np.linalg.norm(tracks.xy - true_xy[:, tracked], axis=-1))
        reference = int(data["pose_neutral_frame"])
        truth_ypr.append(relative_ypr(truth["R"], reference))
        ours_ypr.append(relative_ypr(data["pose_R"], reference))
    rows = []
    for method in ("landmarker", "default", "correlation"):
        err = np.concatenate(errors[method])
        rows += [
            row(f"real_track_err_px_{method}", err.mean(), "px"),
            row(f"real_track_err_px_{method}_p95", np.percentile(err, 95), "px"),
        ]
        if method != "correlation":
            for name, cols in groups.items():
                rows.append(row(f"real_track_err_px_{method}_{name}", err[:, cols].mean(), "px"))
    rows.append(row("real_track_err_px_default_tracked_subset", np.concatenate(errors["default_tracked"]).mean(), "px"))
    rows.append(row("real_track_err_px", np.concatenate(errors["default"]).mean(), "px"))
    truth_ypr, ours_ypr = np.concatenate(truth_ypr), np.concatenate(ours_ypr)
    for k, axis in enumerate(("yaw", "pitch", "roll")):
        rows.append(row(f"real_pose_agree_r_{axis}", follow(truth_ypr[:, k], ours_ypr[:, k])[0], "r"))
    rows.append(row("real_pose_err_deg", np.abs(ours_ypr - truth_ypr).mean(), "deg"))
    return rows


def build_pack(clip: Path, work: Path, cache: Path) -> Path:
    """An actor pack built from ``clip`` by ``pack_build.yaml``: its folder."""
    run_pipeline(clip, work / "packs" / clip.stem, cache=cache, pipeline=REPO / "pack_build.yaml")
    return work / "packs" / clip.stem / "out" / "pack"


WORST = {"recall": min, "precision": min, "_r": min, "amp_ratio": min, "frames": max, "frac": max}
# state measures whose clip row (``real_<key>_<stem>``) is :func:`follow_rows`' on the bundled run:
# their worst over the targets is not a row (each target's is, ``..._onto_<target>``)
NAMED_BY_FOLLOW_ROWS = ("mouth_follow_r", "mouth_amp_ratio")


def worst_over_targets(measured: dict[str, dict[str, float]]) -> dict[str, float]:
    """A clip's state measures (per target: key -> value) reduced to the worst over its targets
    (:data:`WORST` by the key's ending; NaN left out), but for :data:`NAMED_BY_FOLLOW_ROWS`."""
    worst: dict[str, float] = {}
    for key in set().union(*measured.values()) - set(NAMED_BY_FOLLOW_ROWS):
        values = [m[key] for m in measured.values() if key in m and np.isfinite(m[key])]
        pick = next((f for ending, f in WORST.items() if key.endswith(ending)), None)
        if values and pick is not None:
            worst[key] = pick(values)
    return worst


def states_rows(clips: list[Path], work: Path, pack_clips: list[Path]) -> list[dict[str, Any]]:
    """The expression-state rows (:mod:`scripts.real_states`): every clip onto the bundled target and
    onto packs built from ``pack_clips`` (never onto its own), pops onto each such pack, the
    cut-start variant onto the bundled target, the occluder variant; per clip the worst over its
    targets, then the aggregates over the clips."""
    from scripts import real_states as states
    from scripts.occluder import aggregate_rows

    cache = work / "states_cache"
    targets: dict[str, Path | None] = {"bundled": None}
    targets |= {clip.stem: build_pack(clip, work, cache) for clip in pack_clips}
    rows: list[dict[str, Any]] = []
    per_clip: dict[str, dict[str, float]] = {}
    amp_onto: dict[str, dict[str, float]] = {}
    for clip in clips:
        stem, folder = clip.stem, work / "states" / clip.stem
        measured: dict[str, dict[str, float]] = {}
        for name, pack in targets.items():
            if name == stem:
                continue
            extra = ("--input", f"target={pack}") if pack is not None else ()
            run_pipeline(clip, folder / name, *extra, cache=cache)
            data = np.load(folder / name / "out" / "data" / "data.npz")
            measured[name] = states.state_measures(data) | states.coverage_measures(data)
            rows += [
                row(f"real_{key}_{stem}_onto_{name}", value, states.unit_of(key))
                for key, value in measured[name].items()
                if np.isfinite(value)
            ]
            amp_onto.setdefault(name, {})[stem] = measured[name]["mouth_amp_ratio"]
        worst = worst_over_targets(measured)
        pops: dict[str, dict[str, float]] = {}
        for name in targets:
            if name in ("bundled", stem):
                continue
            for mode in ("full", "warp-only"):
                run_pipeline(
                    clip,
                    folder / f"pops_{name}_{mode}",
                    "--input",
                    f"target={targets[name]}",
                    "--set",
                    "synthesize.head_motion=none",
                    "--set",
                    f"synthesize.mode={mode}",
                    cache=cache,
                )
            pops[name] = states.pops_measures(folder / f"pops_{name}_full" / "out", folder / f"pops_{name}_warp-only" / "out")
            rows += [row(f"real_{key}_{stem}_onto_{name}", value, states.unit_of(key)) for key, value in pops[name].items()]
        worst |= {key: max(m[key] for m in pops.values()) for key in next(iter(pops.values()))}
        worst |= states.cutstart_measures(clip, folder / "bundled" / "out", folder, lambda c, f: run_pipeline(c, f, cache=cache))
        rows += [
            row(f"real_{key}_{stem}", value, states.unit_of(key)) for key, value in sorted(worst.items()) if np.isfinite(value)
        ]
        per_clip[stem] = worst
        rows += occlusion_variant_rows(clip, folder / "occlusion", cache)
    rows += states.aggregate(per_clip)
    rows += aggregate_rows(rows, [clip.stem for clip in clips])
    for name, amps in amp_onto.items():
        if name != "bundled":
            rows.append(row(f"real_mouth_amp_ratio_onto_{name}_min", min(amps.values()), "ratio"))
    return rows


def occlusion_variant_rows(clip: Path, work: Path, cache: Path) -> list[dict[str, Any]]:
    """Benchmark variant (b): a synthetic hand over the mouth, then over one eye, 30 frames each
    (:func:`scripts.occluder.occlusion_rows`: recall and precision of ``occlusion.detect``,
    false alarms on the clean clip), and the default pipeline on that variant against the same
    clip re-encoded alike without the hand: ``real_occlusion_outside_diff_<stem>``, the median over
    the frames away from the hands (3 frames either side) of the largest target point difference,
    eye distances, beside ``real_occlusion_outside_landmark_diff_<stem>``, the same of the
    performer's landmarks (what re-encoding alone moves them)."""
    from scripts.occluder import occlusion_rows, write_variant
    from stages.geometry.mapping import eye_distance

    rows = occlusion_rows(clip, work, half=False)
    points = np.load(work / "points.npz")
    names = [str(n) for n in points["names"]]
    write_variant(clip, work / "clean.mp4", points["xy"], names, [])
    for name in ("clean", "occluded"):
        run_pipeline(work / f"{name}.mp4", work / f"run_{name}", cache=cache)
    a, b = (np.load(work / f"run_{name}" / "out" / "data" / "data.npz") for name in ("occluded", "clean"))
    truth = np.load(work / "occluded_truth.npz")
    away = np.ones(len(a["target_xy"]), bool)
    for first, stop in truth["events"]:
        away[max(0, first - 3) : stop + 3] = False
    out = []
    for key, label in (("target", "outside_diff"), ("tracked", "outside_landmark_diff")):
        scale = eye_distance(np.nanmedian(b[f"{key}_xy"], axis=0), names)
        diff = np.nanmax(np.linalg.norm(a[f"{key}_xy"] - b[f"{key}_xy"], axis=-1), axis=1) / scale
        out.append(row(f"real_occlusion_{label}_{clip.stem}", float(np.nanmedian(diff[away])), "eye"))
    return rows + out


def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(prog="bench.py real")
    parser.add_argument("--clip", action="append", type=Path, default=[], help="a real clip (repeatable)")
    parser.add_argument("--realtex-frames", type=int, default=150, help="frames of each real-texture clip")
    parser.add_argument("--realtex-seeds", default="1,2", help="seeds of the real-texture clips")
    parser.add_argument("--no-realtex", action="store_true", help="skip the real-texture clips")
    parser.add_argument("--no-clips", action="store_true", help="skip the real clips' own rows (--target still maps them)")
    parser.add_argument("--target", type=Path, help="also map each clip onto this actor pack (real_cross_ rows)")
    parser.add_argument(
        "--cross-sheet", type=Path, help="with --target: write the points | result sheet here (.png, or .jpg at quality 88)"
    )
    parser.add_argument("--no-states", action="store_true", help="skip the expression-state rows (scripts/real_states.py)")
    parser.add_argument("--states-sheet", type=Path, help="write the real-texture states contact sheet here (.png or .jpg)")
    parser.add_argument(
        "--pack-from",
        action="append",
        type=Path,
        default=[],
        help="state rows: also map onto a pack built from this clip (repeatable; default: the dev "
        f"clips {', '.join(PACK_CLIPS)})",
    )
    options = parser.parse_args(args.extra)
    work = Path(args.work) / BENCH
    rows: list[dict[str, Any]] = []
    if not options.no_realtex:
        seeds = [int(s) for s in options.realtex_seeds.split(",") if s]
        rows += realtex_rows(work, options.realtex_frames, seeds)
    clips = options.clip or (sorted(DEV_CLIPS.glob("*.mp4")) if DEV_CLIPS.is_dir() else [])
    if not options.no_clips and clips:
        for clip in clips:
            rows += clip_rows(clip, work / clip.stem)
        rows += aggregate(rows, [c.stem for c in clips])
        rows += pack_image_rows(TARGET_PACK, "real")
    if options.target is not None and clips:
        rows += cross_rows(clips, work, options.target.resolve(), options.cross_sheet)
    if options.states_sheet is not None:
        from scripts.real_states import states_sheet

        states_sheet(work / "states_sheet", options.states_sheet, lambda c, f: run_pipeline(c, f))
    if not options.no_states and clips:
        pack_clips = options.pack_from or [DEV_CLIPS / name for name in PACK_CLIPS if (DEV_CLIPS / name).is_file()]
        rows += states_rows(clips, work, pack_clips)
    return rows
