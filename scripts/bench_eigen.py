"""Eigenfeature benchmark (Valente & Dugelay) beside point tracking, on the fixture clips and on
real clips.

    python scripts/bench.py eigen [--json] [--work DIR] [--fixtures DIR] [--samples N] [--q Q]
                                  [--blur PX] [--ridge A] [--figure PNG] [--no-fixtures]
                                  [--clip PATH ...] [--no-clips] [--build-fraction 0.6]

**Fixture clips** (truth known).

The performer's face model (the generator's identity of ``packs/performer``) is rendered under
two samplings (the renders cached under ``--work``, about 230 MB) and a model trained on each
(patch blur 1 px, q = 16, the stage's defaults): ``paper`` (each of the 12
parameters alone over 5 levels x 9 orientations, X/Y rotation in {-3, 0, 3} deg: 441 renders)
and ``rich`` (the paper's set plus ``--samples`` random combinations, yaw +-25, pitch +-15,
roll +-10 deg). Rows, for S in (paper, rich) and clip C in (calm, live), frames 1..T-1:

- ``eigen_train_s_S``: training time (renders, patches, PCA, estimator), s;
  ``eigen_fps_S``: analysis frames/s (patches, scores, estimator; frames decoded beforehand).
- ``eigen_param_err_S_C``: mean absolute error of the 12 estimated parameters (controls in
  [0, 1]) against the truth, normalization (similarity) and rotation from the tracked points as
  the pipeline runs it; ``..._truepose``: with the true similarity and rotation;
  ``..._ridge``: the ridge estimator (``--ridge``); ``eigen_param_err_neutral_C``: all zero.
- ``eigen_disp_err_px_S_C``: mean distance of the estimated displacements of all 134 points in
  the neutral's frame (``analyze.eigenfeatures``' ``displacements``, what the mapping gets) to the
  truth ``expression_points - neutral_points``; ``..._on_tracked``: over the 36 tracked points;
  ``..._trueparams``: the true parameters through the model's linear parameter -> geometry map
  (the floor of this reading); per feature F (eye_l, eye_r, mouth: its tracked points)
  ``eigen_disp_err_px_F_S_C``. Beside them the point tracker's displacements (NCC with the face
  model, Gaussian smoothing, face-model pose, ``compensate.pose3d``, as pipeline.yaml runs it)
  on the tracked points, ``eigen_disp_err_px_tracked[_F]_C``, and the neutral's (all zero),
  ``eigen_disp_err_px_neutral[_F]_C``.
- ``eigen_geom_err_px_S_C``: the same geometry placed in the frame by the tracked similarity
  (``points``), mean distance of all points to the truth where visible; ``..._on_tracked``; the
  tracker's smoothed points ``eigen_geom_err_px_tracked_C``; the neutral through the same
  similarity ``eigen_geom_err_px_neutral[_on_tracked]_C``.
- ``eigen_param_err_S_C_<variant>``: the parameter error of models with other patch settings
  (:data:`VARIANTS`: no blur, per-patch normalization, q = 32).
- ``eigen_pose_leak_S``: 4 expressions rendered at yaw x pitch in {-10, -5, 0, 5, 10}^2 deg
  (true similarity and rotation): the spread (max - min) over poses of each estimated parameter,
  mean over parameters and expressions, relative to the parameters' range [0, 1];
  ``eigen_pose_leak_norot_S``: the same estimator without the rotation in its observation.
- Headline rows (names the team's checks read): ``eigen_geom_err_px``, ``_neutral``, ``_tracked``
  (the in-frame geometry rows above for the default ``rich`` sampling, the neutral and the tracker,
  each the mean of calm and live), ``eigen_pose_leak`` and ``eigen_pose_leak_norot`` (``rich``).

**Real clips** (``--clip PATH``, repeatable; default every ``*.mp4`` of ``../shared/dev-clips/``;
no truth). Per clip (suffix ``_<clip stem>``): a performer pack from the first
``--build-fraction`` of the frames (``scripts/bench_reenact.build_pack``: the landmark and pack
stages), then ``pipeline.yaml`` (the point path) and ``pipeline_eigen_real.yaml`` with that pack
(the eigenfeature path; its training renders the pack) on the whole clip, sharing one cache, and
the expression-follow measures of ``bench real`` (:func:`stages.geometry.signals.follow` of the
target geometry's signal against the performer's landmarks') over the frames after the build
part: ``eigen_real_mouth_r``, ``eigen_real_mouth_amp``, ``eigen_real_brow_r``,
``eigen_real_brow_amp`` (eigenfeatures) and ``eigen_real_points_mouth_r`` ... (the point path);
``eigen_real_params`` (PCA parameters of the pack), ``eigen_real_train_s`` (the training stage:
renders, PCA, estimator), ``eigen_real_fps`` (the analysis stage, frames/s),
``eigen_real_test_frames``, ``eigen_real_load`` (the 1-minute load average when the clip
started: the machine is shared).
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

import cv2
import numpy as np

from scripts.bench_geometry import SMOOTH_SIGMA, decode
from stages.actor_pack import load_pack
from stages.eigen.model import EigenModel, analyze_frames, parameters_to_points
from stages.eigen.patches import FEATURES, feature_points
from stages.eigen.packface import pca_parameters
from stages.eigen.sampling import rich_sampling
from stages.geometry.rotation import ypr_zyx
from stages.eigen.synthetic import PerformerRig, performer_rig
from stages.eigen.training import train_on_renders, training_samples
from stages.geometry.compensate import compensate, fit_similarity
from stages.geometry.face_model import pack_face_model
from stages.geometry.frontalize import adapt_to_reference, frontalize
from stages.geometry.pose import estimate_face_poses
from stages.geometry.smooth import gaussian_smooth
from stages.geometry.track import read_first_frame_points, track_points

AREA = "eigen"
REPO = Path(__file__).resolve().parent.parent
DEV_CLIPS = REPO.parent / "shared" / "dev-clips"
SIGNALS = (("mouth_open", "mouth"), ("brow_raise", "brow"))
SAMPLINGS = ("paper", "rich")
LEAK_DEG = (-10.0, -5.0, 0.0, 5.0, 10.0)
LEAK_EXPRESSIONS = 4
BLUR_PX = 1.0  # train.eigenfeatures' default
VARIANTS = {"noblur": {"blur_px": 0.0}, "norm": {"normalize": True}, "q32": {"q": 32}}  # rows ..._<label>


def row(metric: str, value: float, unit: str) -> dict[str, Any]:
    return {"bench": AREA, "metric": metric, "value": float(value), "unit": unit}


def training_renders(rig: PerformerRig, sampling: str, *, samples: int, work: Path) -> dict[str, np.ndarray]:
    """The training renders of ``sampling`` (images, similarities, controls, angles, render
    time), cached under ``work``: models with other patch settings reuse them."""
    path = work / f"eigen_renders_{sampling}_n{samples}.npz"
    if path.is_file():
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    controls, angles = rig.sampling(sampling, samples=samples, seed=0)
    start = time.perf_counter()
    images, sims = zip(*training_samples(rig, controls, angles))
    out = {
        "images": np.stack(images),
        "similarity": np.stack(sims),
        "controls": controls,
        "angles": angles,
        "render_s": np.array(time.perf_counter() - start),
    }
    work.mkdir(parents=True, exist_ok=True)
    np.savez(path, **out)
    return out


def trained(rig: PerformerRig, renders: dict[str, np.ndarray], **options: Any) -> tuple[EigenModel, float]:
    """A model from cached renders and its training time (s): the renders' time plus the fit's."""
    start = time.perf_counter()
    model = train_on_renders(
        rig, renders["controls"], renders["angles"], samples=zip(renders["images"], renders["similarity"]), **options
    )
    return model, float(renders["render_s"]) + time.perf_counter() - start


def tracked_path(root: Path, kind: str, frames: list[np.ndarray]) -> dict[str, np.ndarray]:
    """The pipeline's point-tracking reading of a clip: smoothed tracked points, their columns in
    the layout, the similarity of the rigid points and the head rotation of the face model."""
    pack = load_pack(root / "packs" / "performer")
    layout = pack.layout
    names, init, _ = read_first_frame_points(root / "clips" / f"{kind}_track0.csv")
    rigid = np.array([names.index(layout.point_names[i]) for i in layout.rigid])
    face_model = pack_face_model(pack, names, init, rigid, pack.intrinsics)
    tracks = track_points(iter(frames), init, method="ncc", face_model=face_model)
    smoothed, valid = gaussian_smooth(tracks.xy, tracks.valid, sigma=SMOOTH_SIGMA)
    sim = compensate(smoothed, valid, smoothed[0], rigid)
    pose = estimate_face_poses(smoothed, valid, face_model)
    columns = np.array([layout.index(n) for n in names])
    model3d = adapt_to_reference(pack.model3d[columns], smoothed[0], pose["R"][0], pose["tvec"][0], pack.intrinsics)
    frontal, _ = frontalize(smoothed, model3d, pose["R"], pose["tvec"], pack.intrinsics, reference=0)
    return {
        "xy": smoothed,
        "d": frontal - smoothed[:1],
        "columns": columns,
        "similarity": sim["params"],
        "valid": sim["frame_valid"] & pose["valid"],
        "angles": ypr_zyx(pose["R"]),
    }


def distances(xy: np.ndarray, truth: np.ndarray, visible: np.ndarray) -> float:
    """Mean distance px over frames 1.. where visible."""
    return float(np.linalg.norm(xy - truth, axis=2)[1:][visible[1:]].mean())


def feature_columns(model: EigenModel, columns: np.ndarray) -> dict[str, np.ndarray]:
    """Per feature, the positions in ``columns`` (the tracked points) of its points."""
    out = {}
    for feature, prefixes in FEATURES.items():
        members = set(feature_points(model.point_names, prefixes))
        out[feature] = np.array([k for k, c in enumerate(columns) if c in members])
    return out


def clip_rows(
    model: EigenModel,
    sampling: str,
    kind: str,
    frames: list[np.ndarray],
    truth: dict[str, np.ndarray],
    tracked: dict[str, np.ndarray],
    ridge: float,
) -> tuple[list[dict[str, Any]], np.ndarray, float]:
    """Rows of one model on one clip; returns them, the parameters estimated on the tracked
    path and the analysis frames/s."""
    T = len(frames)
    start = time.perf_counter()
    mu, _ = analyze_frames(model, frames, tracked["similarity"], tracked["valid"], tracked["angles"])
    fps = T / (time.perf_counter() - start)
    true_mu, _ = analyze_frames(model, frames, truth["similarity"], np.ones(T, bool), ypr_zyx(truth["R"]))
    ridge_mu, _ = analyze_frames(model, frames, tracked["similarity"], tracked["valid"], tracked["angles"], ridge=ridge)
    controls = truth["controls"]
    suffix = f"_{sampling}_{kind}"
    rows = [
        row(f"eigen_param_err{suffix}", np.nanmean(np.abs(mu - controls)[1:]), "control units"),
        row(f"eigen_param_err{suffix}_truepose", np.nanmean(np.abs(true_mu - controls)[1:]), "control units"),
        row(f"eigen_param_err{suffix}_ridge", np.nanmean(np.abs(ridge_mu - controls)[1:]), "control units"),
    ]
    mu = np.nan_to_num(mu)
    xy = parameters_to_points(model, mu, tracked["similarity"])
    d = parameters_to_points(model, mu) - model.neutral
    true_d = truth["expression_points"] - truth["neutral_points"]
    ideal_d = parameters_to_points(model, controls) - model.neutral
    points, visible, cols = truth["points"], truth["visible"], tracked["columns"]
    everywhere = np.ones_like(visible)
    rows += [
        row(f"eigen_disp_err_px{suffix}", distances(d, true_d, everywhere), "px"),
        row(f"eigen_disp_err_px_on_tracked{suffix}", distances(d[:, cols], true_d[:, cols], everywhere[:, cols]), "px"),
        row(f"eigen_disp_err_px_trueparams{suffix}", distances(ideal_d, true_d, everywhere), "px"),
        row(f"eigen_geom_err_px{suffix}", distances(xy, points, visible), "px"),
        row(f"eigen_geom_err_px_on_tracked{suffix}", distances(xy[:, cols], points[:, cols], visible[:, cols]), "px"),
    ]
    for feature, use in feature_columns(model, cols).items():
        rows.append(
            row(
                f"eigen_disp_err_px_{feature}{suffix}",
                distances(d[:, cols[use]], true_d[:, cols[use]], everywhere[:, cols[use]]),
                "px",
            )
        )
    return rows, mu, fps


def tracked_rows(
    model: EigenModel, kind: str, truth: dict[str, np.ndarray], tracked: dict[str, np.ndarray]
) -> list[dict[str, Any]]:
    """The point tracker's and the do-nothing baseline's rows on one clip."""
    points, visible, cols = truth["points"], truth["visible"], tracked["columns"]
    true_d = (truth["expression_points"] - truth["neutral_points"])[:, cols]
    everywhere = np.ones_like(true_d[..., 0], dtype=bool)
    neutral = parameters_to_points(model, np.zeros((len(points), len(model.param_names))), tracked["similarity"])
    rows = [
        row(f"eigen_disp_err_px_tracked_{kind}", distances(tracked["d"], true_d, everywhere), "px"),
        row(f"eigen_disp_err_px_neutral_{kind}", distances(0 * true_d, true_d, everywhere), "px"),
        row(f"eigen_geom_err_px_tracked_{kind}", distances(tracked["xy"], points[:, cols], visible[:, cols]), "px"),
        row(f"eigen_geom_err_px_neutral_{kind}", distances(neutral, points, visible), "px"),
        row(f"eigen_geom_err_px_neutral_on_tracked_{kind}", distances(neutral[:, cols], points[:, cols], visible[:, cols]), "px"),
        row(f"eigen_param_err_neutral_{kind}", np.abs(truth["controls"][1:]).mean(), "control units"),
    ]
    for feature, use in feature_columns(model, cols).items():
        rows += [
            row(
                f"eigen_disp_err_px_tracked_{feature}_{kind}",
                distances(tracked["d"][:, use], true_d[:, use], everywhere[:, use]),
                "px",
            ),
            row(
                f"eigen_disp_err_px_neutral_{feature}_{kind}",
                distances(0 * true_d[:, use], true_d[:, use], everywhere[:, use]),
                "px",
            ),
        ]
    return rows


def leak_renders(rig: PerformerRig, work: Path) -> dict[str, np.ndarray]:
    """The pose-decoupling set: expressions x (yaw, pitch) renders with their true similarity
    and angles (cached under ``work``)."""
    path = work / "eigen_leak_renders.npz"
    if path.is_file():
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    controls, _ = rich_sampling(len(rig.param_names), LEAK_EXPRESSIONS, seed=99, active=0.5)
    rigid = list(rig.face.layout.rigid)
    neutral = rig.points(np.zeros(len(rig.param_names)))
    images, sims, angles = [], [], []
    for c in controls:
        for yaw in LEAK_DEG:
            for pitch in LEAK_DEG:
                image, pts = rig.render(c, np.array([yaw, pitch, 0.0]))
                images.append(image)
                sims.append(fit_similarity(neutral[rigid], pts[rigid]))
                angles.append((yaw, pitch, 0.0))
    out = {"images": np.stack(images), "similarity": np.stack(sims), "angles": np.array(angles), "controls": controls}
    work.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **out)
    return out


def leak_rows(model: EigenModel, sampling: str, renders: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    """Spread of the estimated parameters across poses of the same expression, with and without
    rotation in the estimator."""
    n = len(renders["images"])
    rows = []
    for label, angles in (("", renders["angles"]), ("_norot", None)):
        mu, _ = analyze_frames(model, renders["images"], renders["similarity"], np.ones(n, bool), angles)
        per_expression = mu.reshape(len(renders["controls"]), -1, mu.shape[1])
        spread = per_expression.max(axis=1) - per_expression.min(axis=1)
        rows.append(row(f"eigen_pose_leak{label}_{sampling}", spread.mean(), "fraction of range"))
    return rows


def figure(rig: PerformerRig, frames: list[np.ndarray], mu: np.ndarray, angles: np.ndarray, path: Path) -> None:
    """Fig. 2 of the paper: input frames above, the estimated parameters rendered (at the
    tracked rotation) below."""
    picks = np.linspace(4, len(frames) - 1, 5).round().astype(int)
    face = rig.points(np.zeros(len(rig.param_names)))
    (x0, y0), (x1, y1) = (face.min(axis=0) - 12).astype(int).clip(0), (face.max(axis=0) + 12).astype(int)
    crop = (slice(y0, y1 + 1), slice(x0, x1 + 1))
    top = [frames[t][crop] for t in picks]
    bottom = [rig.render(mu[t], angles[t])[0][crop] for t in picks]
    sheet = np.vstack([np.hstack(top), np.hstack(bottom)])
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])


def fixture_rows(own: argparse.Namespace, work: Path) -> list[dict[str, Any]]:
    """The rows of the fixture clips (module docstring)."""
    root = own.fixtures
    rig = performer_rig(root / "packs" / "performer")
    renders = {sampling: training_renders(rig, sampling, samples=own.samples, work=work) for sampling in SAMPLINGS}
    models, variants = {}, {}
    rows: list[dict[str, Any]] = []
    for sampling in SAMPLINGS:
        models[sampling], seconds = trained(rig, renders[sampling], q=own.q, blur_px=own.blur)
        rows.append(row(f"eigen_train_s_{sampling}", seconds, "s"))
        for label, options in VARIANTS.items():
            variants[(sampling, label)] = trained(rig, renders[sampling], **{"q": own.q, "blur_px": own.blur, **options})[0]
    estimates = {}
    for kind in ("calm", "live"):
        frames = decode(root / "clips" / f"{kind}.mp4")
        with np.load(root / "clips" / f"{kind}_truth.npz", allow_pickle=False) as data:
            truth = {k: data[k] for k in data.files}
        tracked = tracked_path(root, kind, frames)
        rows += tracked_rows(models["paper"], kind, truth, tracked)
        for sampling in SAMPLINGS:
            more, mu, fps = clip_rows(models[sampling], sampling, kind, frames, truth, tracked, own.ridge)
            rows += more
            if kind == "live":
                rows.append(row(f"eigen_fps_{sampling}", fps, "frames/s"))
            estimates[(sampling, kind)] = (frames, mu, tracked["angles"])
            for label in VARIANTS:
                v_mu, _ = analyze_frames(
                    variants[(sampling, label)], frames, tracked["similarity"], tracked["valid"], tracked["angles"]
                )
                rows.append(
                    row(
                        f"eigen_param_err_{sampling}_{kind}_{label}",
                        np.nanmean(np.abs(v_mu - truth["controls"])[1:]),
                        "control units",
                    )
                )
    leak = leak_renders(rig, work)
    for sampling in SAMPLINGS:
        rows += leak_rows(models[sampling], sampling, leak)
    frames, mu, angles = estimates[("rich", "calm")]
    figure(rig, frames, mu, angles, own.figure or work / "eigen_fig2.png")
    return rows + headline_rows(rows)


def run_pipeline(pipeline: Path, clip: Path, out: Path, cache: Path, *extra: str) -> dict[str, float]:
    """Run ``pipeline`` on ``clip`` up to its ``data`` stage (outputs under ``out``, stages cached
    in ``cache``); return each stage's own seconds (from ``--log-json``)."""
    log = out.parent / f"{out.name}.jsonl"
    command = [
        sys.executable,
        "-c",
        "from runner.cli import main; main()",
        "run",
        str(pipeline),
        "--in",
        str(clip),
        "--out",
        str(out),
        "--cache-dir",
        str(cache),
        "--log-json",
        str(log),
        "--until",
        "data",
        *extra,
    ]
    result = subprocess.run(command, cwd=REPO, env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True, text=True)
    if result.returncode != 0:
        raise SystemExit(f"{pipeline.name} failed on {clip} ({result.returncode}): {result.stderr.strip()[-2000:]}")
    events = [json.loads(line) for line in log.read_text().splitlines()]
    return {e["stage"]: float(e.get("seconds", 0.0)) for e in events if e.get("event") == "stage"}


def follow_rows(data_npz: Path, test: np.ndarray, prefix: str, stem: str) -> list[dict[str, Any]]:
    """Mouth and brow follow (Pearson r, amplitude ratio) of a run's target geometry against the
    performer's landmarks over the ``test`` frames ``(T,)`` bool, as ``bench real`` measures them."""
    from stages.geometry.signals import expression_signals, follow

    with np.load(data_npz, allow_pickle=False) as data:
        names = [str(n) for n in data["target_names"]]
        performer = expression_signals(data["tracked_xy"], names)
        target = expression_signals(data["target_xy"], names)
        valid = data["tracked_valid"].all(axis=1) & test
    rows = []
    for signal, short in SIGNALS:
        r, ratio = follow(performer[signal], target[signal], valid)
        rows += [row(f"{prefix}_{short}_r_{stem}", r, "r"), row(f"{prefix}_{short}_amp_{stem}", ratio, "ratio")]
    return rows


def real_clip_rows(clip_path: Path, work: Path, build_fraction: float) -> list[dict[str, Any]]:
    """The eigenfeature path beside the point path on one real clip (module docstring)."""
    from scripts.bench_reenact import build_pack, decode as decode_clip
    from stages.actor_pack import load_pack as load

    stem = clip_path.stem
    load_1min = os.getloadavg()[0]
    work.mkdir(parents=True, exist_ok=True)
    clip = decode_clip(clip_path)
    T = clip.info.frames
    build = int(round(build_fraction * T))
    pack_dir = build_pack(clip, work, build, {})[0]
    print(f"bench eigen: {stem}: pack built from frames 0-{build - 1} in {pack_dir}", file=sys.stderr, flush=True)
    cache = work / "cache"
    run_pipeline(REPO / "pipeline.yaml", clip_path, work / "points", cache)
    seconds = run_pipeline(
        REPO / "pipeline_eigen_real.yaml", clip_path, work / "eigen", cache, "--input", f"performer_pack={pack_dir}"
    )
    test = np.arange(T) >= build
    rows = follow_rows(work / "eigen" / "data" / "data.npz", test, "eigen_real", stem)
    rows += follow_rows(work / "points" / "data" / "data.npz", test, "eigen_real_points", stem)
    return rows + [
        row(f"eigen_real_params_{stem}", len(pca_parameters(load(pack_dir).captured_points)), "parameters"),
        row(f"eigen_real_train_s_{stem}", seconds["train_eigen"], "s"),
        row(f"eigen_real_fps_{stem}", T / max(seconds["eigen"], 1e-9), "frames/s"),
        row(f"eigen_real_test_frames_{stem}", T - build, "frames"),
        row(f"eigen_real_load_{stem}", load_1min, "load"),
    ]


def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(prog="bench.py eigen")
    parser.add_argument("--fixtures", type=Path, default=Path("fixtures"), help="CI fixture set (clips/, packs/)")
    parser.add_argument("--samples", type=int, default=500, help="random combinations of the rich sampling")
    parser.add_argument("--q", type=int, default=16, help="eigenfeatures per feature")
    parser.add_argument("--blur", type=float, default=BLUR_PX, help="patch blur, px (analyze/train default)")
    parser.add_argument("--ridge", type=float, default=1e-3, help="ridge of the ..._ridge rows")
    parser.add_argument("--figure", type=Path, default=None, help="write the Fig. 2 sheet here (default: under --work)")
    parser.add_argument("--no-fixtures", action="store_true", help="skip the fixture clips")
    parser.add_argument("--clip", type=Path, action="append", default=[], help="a real clip (repeatable)")
    parser.add_argument("--no-clips", action="store_true", help="skip the real clips")
    parser.add_argument("--build-fraction", type=float, default=0.6, help="share of a real clip the pack is built from")
    own = parser.parse_args(args.extra)
    work = Path(args.work)
    rows = [] if own.no_fixtures else fixture_rows(own, work)
    clips = own.clip or (sorted(DEV_CLIPS.glob("*.mp4")) if DEV_CLIPS.is_dir() else [])
    if not own.no_clips:
        for clip in clips:
            rows += real_clip_rows(clip, work / "eigen_real" / clip.stem, own.build_fraction)
    return rows


def headline_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The rows the team's checks read: the default (``rich``) sampling's in-frame geometry error,
    the neutral's and the point tracker's, each the mean over the two clips, and its pose leak
    with and without the rotation input."""
    value = {r["metric"]: r["value"] for r in rows}

    def over_clips(name: str) -> float:
        return float(np.mean([value[f"{name}_{kind}"] for kind in ("calm", "live")]))

    return [
        row("eigen_geom_err_px", over_clips("eigen_geom_err_px_rich"), "px"),
        row("eigen_geom_err_px_neutral", over_clips("eigen_geom_err_px_neutral"), "px"),
        row("eigen_geom_err_px_tracked", over_clips("eigen_geom_err_px_tracked"), "px"),
        row("eigen_pose_leak", value["eigen_pose_leak_rich"], "fraction of range"),
        row("eigen_pose_leak_norot", value["eigen_pose_leak_norot_rich"], "fraction of range"),
    ]
