"""Rows for the geometry benchmark: 3D motion compensation (``compensate.pose3d``) against the
paper's 2D similarity (``compensate.similarity``) on the fixture clips.

    python scripts/bench_frontalize.py [--fixtures DIR] [--no-tracker]   # JSON lines

``scripts/bench_geometry.py`` adds these rows with ``bench_rows(fixtures)``. Per clip (``calm``,
``live``), ``<c>`` = ``compensate3d`` (pose.pnp -> compensate.pose3d) or ``compensate2d``
(compensate.similarity, the baseline measured in the same run), on the clip's true 2D points of
the tracked subset (``_truth.npz``):

- ``<c>_err_px_<clip>``: mean distance of the compensated tracked points (neutral + d) to the
  ideal compensation ``expression_points`` (the points projected without head motion);
  ``compensate3d_truepose_err_px_<clip>``: the same with the generator's pose instead of PnP's.
- ``<c>_chain_err_px_<clip>_<mode>``: the chain compensate -> map.expression (each ``mode``) ->
  propagate.hierarchical (target pack's hierarchical PCA), mean distance over all N points to the
  ideal mapping ``target_points``; ``chain_neutral_err_px_<clip>``: the target's neutral left
  as it is (the do-nothing baseline).
- with the tracker (default): ``<c>_tracked_chain_err_px_<clip>_none``: the same chain from
  the pipeline's tracked points (the ``track.correlation`` stage with the performer pack's bundles ->
  ``smooth.gaussian``) and its pose (``pose.pnp`` with ``model: face``);
  ``compensate3d_tracked_chain_err_px_<clip>_none_eyes_nose``: with pose.pnp given the four eye
  corners and four nose points instead of the rigid set (the hairline tracks worst under yaw).
- ``compensate3d_fps_live``: frames per second of the computation of ``compensate.pose3d``
  (model adaptation and :func:`frontalize`, pack loading excluded) on the live clip, and
  ``compensate3d_fps_ratio_vs_2d``: over the fps of the eq. 8-9 :func:`compensate` in the same run.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from runner.stage import Context, StreamInfo
from runner.streams import ComputedStream, chunk_ranges
from stages.actor_pack import load_pack
from stages.geometry.compensate import SimilarityCompensate, compensate
from stages.geometry.frontalize import PoseCompensate, adapt_to_reference, frontalize
from stages.geometry.mapping import MODES as MAP_MODES
from stages.geometry.mapping import ExpressionMap
from stages.geometry.pose import PnPPose
from stages.geometry.subset import named_columns
from stages.geometry.track import CorrelationTrack
from stages.pack.bundles import camera_from_bundle, layout_from_bundle, model3d_from_bundle, pack_to_bundles
from stages.propagation.stage import HierarchicalPropagation, TrainHierarchicalPCA

AREA = "geometry"
CLIPS = ("calm", "live")
PIPELINE_POSE = {"model": "face"}  # pose.pnp's parameters in pipeline.yaml
Bundles = Mapping[str, Mapping[str, np.ndarray]]  # pack.load's outputs by port
EYES_NOSE = ["eye_l_0", "eye_r_0", "eye_l_6", "eye_r_6", "nose_tip", "nose_ala_l", "nose_ala_r", "nose_base"]


def row(metric: str, value: float, unit: str) -> dict[str, Any]:
    return {"bench": AREA, "metric": metric, "value": float(value), "unit": unit}


def truth_points(truth: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The clip's true positions of the tracked subset as a ``points`` bundle."""
    tracked = truth["tracked"]
    return {
        "xy": truth["points"][:, tracked],
        "valid": np.ones((len(truth["points"]), len(tracked)), bool),
        "names": truth["point_names"][tracked],
        "fps": truth["fps"],
        "size": truth["size"],
    }


def ports(pack: Bundles, *names: str) -> Bundles:
    """The bundles of ``pack.load``'s outputs ``names``, as a stage's inputs."""
    return {name: pack[name] for name in names}


def tracker_points(clip: Path, init: Path, performer: Bundles, ctx: Context) -> dict[str, np.ndarray]:
    """The tracker's points of a clip as the pipeline makes them: the ``track.correlation``
    stage with its defaults given the performer pack's bundles (pipeline_paper.yaml) and the
    first-frame CSV, then the ``smooth.gaussian`` stage with its defaults; a ``points`` bundle."""
    from scripts.bench_geometry import decode
    from stages.geometry.smooth import GaussianSmooth

    frames = np.stack(decode(clip))
    height, width = frames.shape[1:3]
    ranges = chunk_ranges(len(frames), 16)
    stream = ComputedStream(
        StreamInfo(len(frames), 25.0, width, height),
        ranges,  # fps: no row reads it
        lambda index: frames[ranges[index][0] : ranges[index][1]],
    )
    inputs = {"frames": stream, "init": init, **ports(performer, "model3d", "geometry", "camera")}
    tracked = CorrelationTrack().run(inputs, {}, ctx)["points"]
    return GaussianSmooth().run({"points": tracked}, {}, ctx)["points"]


def pose(
    points: Mapping[str, np.ndarray], performer: Bundles, ctx: Context, params: Mapping[str, Any] | None = None
) -> dict[str, np.ndarray]:
    """The ``pose.pnp`` stage's pose with ``params`` (its defaults when None)."""
    inputs = {"points": points, **ports(performer, "layout", "model3d", "camera", "geometry")}
    return PnPPose().run(inputs, dict(params or {}), ctx)["pose"]


def pose_compensate(
    points: Mapping[str, np.ndarray], pose: Mapping[str, np.ndarray], performer: Bundles, ctx: Context
) -> dict[str, np.ndarray]:
    """The ``compensate.pose3d`` stage's displacements."""
    inputs = {"points": points, "pose": pose, **ports(performer, "model3d")}
    return PoseCompensate().run(inputs, {}, ctx)["displacements"]


def compensations(
    points: Mapping[str, np.ndarray],
    performer: Bundles,
    ctx: Context,
    truth: Mapping[str, np.ndarray] | None = None,
    pose_params: Mapping[str, Any] | None = None,
) -> dict[str, dict[str, np.ndarray]]:
    """Displacement bundles of ``compensate2d``, ``compensate3d`` (the ``pose.pnp`` stage with
    ``pose_params``) and, given the truth, ``compensate3d_truepose``."""
    solved = pose(points, performer, ctx, pose_params)
    out = {
        "compensate2d": SimilarityCompensate().run({"points": points}, {}, ctx)["displacements"],
        "compensate3d": pose_compensate(points, solved, performer, ctx),
    }
    if truth is not None:
        true_pose = {
            "R": truth["R"],
            "tvec": truth["tvec"],
            "rvec": truth["rvec"],
            "valid": np.ones(len(truth["R"]), bool),
            "camera": truth["intrinsics"],
        }
        out["compensate3d_truepose"] = pose_compensate(points, true_pose, performer, ctx)
    return out


def chain_error(
    displacements: Mapping[str, np.ndarray], target: Bundles, pca_model: Any, ideal: np.ndarray, mode: str, ctx: Context
) -> float:
    """Mean px distance over all points of map.expression -> propagate.hierarchical to ``ideal (T, N, 2)``."""
    inputs = {"displacements": displacements, **ports(target, "layout", "geometry")}
    mapped = ExpressionMap().run(inputs, {"mode": mode}, ctx)["points"]
    result = HierarchicalPropagation().run(
        {"pca_model": pca_model, "points": mapped}, {"stop_progress_px": 1e-3, "max_iterations": 200}, ctx
    )["points"]
    return float(np.linalg.norm(result["xy"] - ideal, axis=-1).mean())


def fps(work: Callable[[], Any], n_frames: int, *, repeats: int = 20) -> float:
    """Frames per second of ``work()`` over ``n_frames`` frames (best of ``repeats``)."""
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        work()
        best = min(best, time.perf_counter() - start)
    return n_frames / best


def speeds(points: Mapping[str, np.ndarray], performer: Bundles, ctx: Context) -> tuple[float, float]:
    """Frames per second of the 3D compensation (adaptation + frontalization) and of the 2D one."""
    solved = pose(points, performer, ctx)
    layout = layout_from_bundle(performer["layout"])
    xy, valid, names = points["xy"], points["valid"], [str(n) for n in points["names"]]
    generic = model3d_from_bundle(performer["model3d"], names)
    rigid = named_columns(np.array(names), tuple(layout.point_names[i] for i in layout.rigid))
    R, t, camera = solved["R"], solved["tvec"], camera_from_bundle(performer["camera"])

    def run_3d() -> None:
        frontalize(xy, adapt_to_reference(generic, xy[0], R[0], t[0], camera), R, t, camera)

    return fps(run_3d, len(xy)), fps(lambda: compensate(xy, valid, xy[0], rigid), len(xy))


def bench_rows(fixtures: Path = Path("fixtures"), *, tracker: bool = True) -> list[dict[str, Any]]:
    """The rows listed in the module docstring, for the fixture set under ``fixtures``."""
    ctx = Context(device="cpu", files_dir=lambda port: Path("/nonexistent"))
    performer = pack_to_bundles(load_pack(fixtures / "packs" / "performer"))
    target = pack_to_bundles(load_pack(fixtures / "packs" / "target"))
    pca_model = TrainHierarchicalPCA().run(ports(target, "layout", "geometry"), {"n_components": 8, "variance_kept": 1.0}, ctx)[
        "pca_model"
    ]
    target_neutral = target["geometry"]["neutral"]
    rows = []
    for clip in CLIPS:
        truth = dict(np.load(fixtures / "clips" / f"{clip}_truth.npz", allow_pickle=False))
        points = truth_points(truth)
        ideal = truth["expression_points"][:, truth["tracked"]]
        results = compensations(points, performer, ctx, truth)
        for name, bundle in results.items():
            error = np.linalg.norm(bundle["d"] + bundle["neutral"] - ideal, axis=-1).mean()
            rows.append(row(f"{name}_err_px_{clip}", error, "px"))
        for name in ("compensate2d", "compensate3d"):
            for mode in MAP_MODES:
                rows.append(
                    row(
                        f"{name}_chain_err_px_{clip}_{mode}",
                        chain_error(results[name], target, pca_model, truth["target_points"], mode, ctx),
                        "px",
                    )
                )
        rows.append(
            row(
                f"chain_neutral_err_px_{clip}",
                np.linalg.norm(target_neutral[None] - truth["target_points"], axis=-1).mean(),
                "px",
            )
        )
        if tracker:
            clips = fixtures / "clips"
            tracked = tracker_points(clips / f"{clip}.mp4", clips / f"{clip}_track0.csv", performer, ctx)
            for name, bundle in compensations(tracked, performer, ctx, pose_params=PIPELINE_POSE).items():
                rows.append(
                    row(
                        f"{name}_tracked_chain_err_px_{clip}_none",
                        chain_error(bundle, target, pca_model, truth["target_points"], "none", ctx),
                        "px",
                    )
                )
            bundle = pose_compensate(tracked, pose(tracked, performer, ctx, {"points": EYES_NOSE}), performer, ctx)
            rows.append(
                row(
                    f"compensate3d_tracked_chain_err_px_{clip}_none_eyes_nose",
                    chain_error(bundle, target, pca_model, truth["target_points"], "none", ctx),
                    "px",
                )
            )
        if clip == "live":
            fps_3d, fps_2d = speeds(points, performer, ctx)
            rows += [row("compensate3d_fps_live", fps_3d, "fps"), row("compensate3d_fps_ratio_vs_2d", fps_3d / fps_2d, "x")]
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fixtures", type=Path, default=Path("fixtures"), help="CI fixture set (clips/, packs/)")
    parser.add_argument("--no-tracker", action="store_true", help="skip the chain from the tracker's points")
    args = parser.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # scripts.bench_geometry
    for r in bench_rows(args.fixtures, tracker=not args.no_tracker):
        print(json.dumps(r), flush=True)


if __name__ == "__main__":
    main()
