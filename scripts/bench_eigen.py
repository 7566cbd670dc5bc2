"""Eigenfeature benchmark (Valente & Dugelay) beside point tracking, on the fixture clips.

    python scripts/bench.py eigen [--json] [--work DIR] [--fixtures DIR] [--samples N] [--q Q]
                                  [--blur PX] [--ridge A] [--figure PNG]

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
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from scripts.bench_geometry import SMOOTH_SIGMA, decode
from stages.actor_pack import load_pack
from stages.eigen.model import EigenModel, analyze_frames, parameters_to_points
from stages.eigen.patches import FEATURES, feature_points
from stages.eigen.sampling import rich_sampling, rotation_angles
from stages.eigen.stage import training_sampling
from stages.eigen.synthetic import PerformerRig, performer_rig, train_on_renders, training_samples
from stages.geometry.compensate import compensate, fit_similarity
from stages.geometry.face_model import pack_face_model
from stages.geometry.frontalize import adapt_to_reference, frontalize
from stages.geometry.pose import estimate_face_poses
from stages.geometry.smooth import gaussian_smooth
from stages.geometry.track import read_first_frame_points, track_points

AREA = "eigen"
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
    controls, angles = training_sampling(sampling, len(rig.param_names), samples=samples, seed=0)
    start = time.perf_counter()
    images, sims = zip(*training_samples(rig, controls, angles))
    out = {"images": np.stack(images), "similarity": np.stack(sims), "controls": controls, "angles": angles,
           "render_s": np.array(time.perf_counter() - start)}
    work.mkdir(parents=True, exist_ok=True)
    np.savez(path, **out)
    return out


def trained(rig: PerformerRig, renders: dict[str, np.ndarray], **options: Any) -> tuple[EigenModel, float]:
    """A model from cached renders and its training time (s): the renders' time plus the fit's."""
    start = time.perf_counter()
    model = train_on_renders(rig, renders["controls"], renders["angles"],
                             samples=zip(renders["images"], renders["similarity"]), **options)
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
    return {"xy": smoothed, "d": frontal - smoothed[:1], "columns": columns, "similarity": sim["params"],
            "valid": sim["frame_valid"] & pose["valid"], "angles": rotation_angles(pose["R"])}


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


def clip_rows(model: EigenModel, sampling: str, kind: str, frames: list[np.ndarray], truth: dict[str, np.ndarray],
              tracked: dict[str, np.ndarray], ridge: float) -> tuple[list[dict[str, Any]], np.ndarray, float]:
    """Rows of one model on one clip; returns them, the parameters estimated on the tracked
    path and the analysis frames/s."""
    T = len(frames)
    start = time.perf_counter()
    mu, _ = analyze_frames(model, frames, tracked["similarity"], tracked["valid"], tracked["angles"])
    fps = T / (time.perf_counter() - start)
    true_mu, _ = analyze_frames(model, frames, truth["similarity"], np.ones(T, bool), rotation_angles(truth["R"]))
    ridge_mu, _ = analyze_frames(model, frames, tracked["similarity"], tracked["valid"], tracked["angles"], ridge=ridge)
    controls = truth["controls"]
    suffix = f"_{sampling}_{kind}"
    rows = [row(f"eigen_param_err{suffix}", np.nanmean(np.abs(mu - controls)[1:]), "control units"),
            row(f"eigen_param_err{suffix}_truepose", np.nanmean(np.abs(true_mu - controls)[1:]), "control units"),
            row(f"eigen_param_err{suffix}_ridge", np.nanmean(np.abs(ridge_mu - controls)[1:]), "control units")]
    mu = np.nan_to_num(mu)
    xy = parameters_to_points(model, mu, tracked["similarity"])
    d = parameters_to_points(model, mu) - model.neutral
    true_d = truth["expression_points"] - truth["neutral_points"]
    ideal_d = parameters_to_points(model, controls) - model.neutral
    points, visible, cols = truth["points"], truth["visible"], tracked["columns"]
    everywhere = np.ones_like(visible)
    rows += [row(f"eigen_disp_err_px{suffix}", distances(d, true_d, everywhere), "px"),
             row(f"eigen_disp_err_px_on_tracked{suffix}", distances(d[:, cols], true_d[:, cols], everywhere[:, cols]),
                 "px"),
             row(f"eigen_disp_err_px_trueparams{suffix}", distances(ideal_d, true_d, everywhere), "px"),
             row(f"eigen_geom_err_px{suffix}", distances(xy, points, visible), "px"),
             row(f"eigen_geom_err_px_on_tracked{suffix}", distances(xy[:, cols], points[:, cols], visible[:, cols]),
                 "px")]
    for feature, use in feature_columns(model, cols).items():
        rows.append(row(f"eigen_disp_err_px_{feature}{suffix}",
                        distances(d[:, cols[use]], true_d[:, cols[use]], everywhere[:, cols[use]]), "px"))
    return rows, mu, fps


def tracked_rows(model: EigenModel, kind: str, truth: dict[str, np.ndarray], tracked: dict[str, np.ndarray]
                 ) -> list[dict[str, Any]]:
    """The point tracker's and the do-nothing baseline's rows on one clip."""
    points, visible, cols = truth["points"], truth["visible"], tracked["columns"]
    true_d = (truth["expression_points"] - truth["neutral_points"])[:, cols]
    everywhere = np.ones_like(true_d[..., 0], dtype=bool)
    neutral = parameters_to_points(model, np.zeros((len(points), len(model.param_names))), tracked["similarity"])
    rows = [row(f"eigen_disp_err_px_tracked_{kind}", distances(tracked["d"], true_d, everywhere), "px"),
            row(f"eigen_disp_err_px_neutral_{kind}", distances(0 * true_d, true_d, everywhere), "px"),
            row(f"eigen_geom_err_px_tracked_{kind}", distances(tracked["xy"], points[:, cols], visible[:, cols]), "px"),
            row(f"eigen_geom_err_px_neutral_{kind}", distances(neutral, points, visible), "px"),
            row(f"eigen_geom_err_px_neutral_on_tracked_{kind}",
                distances(neutral[:, cols], points[:, cols], visible[:, cols]), "px"),
            row(f"eigen_param_err_neutral_{kind}", np.abs(truth["controls"][1:]).mean(), "control units")]
    for feature, use in feature_columns(model, cols).items():
        rows += [row(f"eigen_disp_err_px_tracked_{feature}_{kind}",
                     distances(tracked["d"][:, use], true_d[:, use], everywhere[:, use]), "px"),
                 row(f"eigen_disp_err_px_neutral_{feature}_{kind}",
                     distances(0 * true_d[:, use], true_d[:, use], everywhere[:, use]), "px")]
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


def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(prog="bench.py eigen")
    parser.add_argument("--fixtures", type=Path, default=Path("fixtures"), help="CI fixture set (clips/, packs/)")
    parser.add_argument("--samples", type=int, default=500, help="random combinations of the rich sampling")
    parser.add_argument("--q", type=int, default=16, help="eigenfeatures per feature")
    parser.add_argument("--blur", type=float, default=BLUR_PX, help="patch blur, px (analyze/train default)")
    parser.add_argument("--ridge", type=float, default=1e-3, help="ridge of the ..._ridge rows")
    parser.add_argument("--figure", type=Path, default=None, help="write the Fig. 2 sheet here (default: under --work)")
    own = parser.parse_args(args.extra)
    root, work = own.fixtures, Path(args.work)
    rig = performer_rig(root / "packs" / "performer")
    renders = {sampling: training_renders(rig, sampling, samples=own.samples, work=work) for sampling in SAMPLINGS}
    models, variants = {}, {}
    rows: list[dict[str, Any]] = []
    for sampling in SAMPLINGS:
        models[sampling], seconds = trained(rig, renders[sampling], q=own.q, blur_px=own.blur)
        rows.append(row(f"eigen_train_s_{sampling}", seconds, "s"))
        for label, options in VARIANTS.items():
            variants[(sampling, label)] = trained(rig, renders[sampling], **{"q": own.q, "blur_px": own.blur,
                                                                             **options})[0]
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
                v_mu, _ = analyze_frames(variants[(sampling, label)], frames, tracked["similarity"], tracked["valid"],
                                         tracked["angles"])
                rows.append(row(f"eigen_param_err_{sampling}_{kind}_{label}",
                                np.nanmean(np.abs(v_mu - truth["controls"])[1:]), "control units"))
    leak = leak_renders(rig, work)
    for sampling in SAMPLINGS:
        rows += leak_rows(models[sampling], sampling, leak)
    frames, mu, angles = estimates[("rich", "calm")]
    figure(rig, frames, mu, angles, own.figure or work / "eigen_fig2.png")
    return rows + headline_rows(rows)


def headline_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The rows the team's checks read: the default (``rich``) sampling's in-frame geometry error,
    the neutral's and the point tracker's, each the mean over the two clips, and its pose leak
    with and without the rotation input."""
    value = {r["metric"]: r["value"] for r in rows}

    def over_clips(name: str) -> float:
        return float(np.mean([value[f"{name}_{kind}"] for kind in ("calm", "live")]))

    return [row("eigen_geom_err_px", over_clips("eigen_geom_err_px_rich"), "px"),
            row("eigen_geom_err_px_neutral", over_clips("eigen_geom_err_px_neutral"), "px"),
            row("eigen_geom_err_px_tracked", over_clips("eigen_geom_err_px_tracked"), "px"),
            row("eigen_pose_leak", value["eigen_pose_leak_rich"], "fraction of range"),
            row("eigen_pose_leak_norot", value["eigen_pose_leak_norot_rich"], "fraction of range")]
