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
  the pipeline's tracked points (``track.correlation`` with the performer pack ->
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

from runner.stage import Context
from stages.actor_pack import load_pack
from stages.geometry.compensate import SimilarityCompensate, compensate
from stages.geometry.frontalize import PoseCompensate, adapt_to_reference, frontalize
from stages.geometry.mapping import MODES as MAP_MODES
from stages.geometry.mapping import ExpressionMap
from stages.geometry.pose import PnPPose
from stages.geometry.subset import named_columns
from stages.propagation.stage import HierarchicalPropagation, TrainHierarchicalPCA

AREA = "geometry"
CLIPS = ("calm", "live")
PIPELINE_POSE = {"model": "face"}  # pose.pnp's parameters in pipeline.yaml
EYES_NOSE = ["eye_l_0", "eye_r_0", "eye_l_6", "eye_r_6", "nose_tip", "nose_ala_l", "nose_ala_r", "nose_base"]


def row(metric: str, value: float, unit: str) -> dict[str, Any]:
    return {"bench": AREA, "metric": metric, "value": float(value), "unit": unit}


def truth_points(truth: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The clip's true positions of the tracked subset as a ``points`` bundle."""
    tracked = truth["tracked"]
    return {"xy": truth["points"][:, tracked], "valid": np.ones((len(truth["points"]), len(tracked)), bool),
            "names": truth["point_names"][tracked], "fps": truth["fps"], "size": truth["size"]}


def tracker_points(clip: Path, init: Path, performer: Path, ctx: Context) -> dict[str, np.ndarray]:
    """The tracker's points of a clip as the pipeline makes them: NCC tracking with the performer
    pack's face model (as ``track.correlation`` given the pack) from the first-frame CSV, then the
    ``smooth.gaussian`` stage with its defaults; a ``points`` bundle."""
    from scripts.bench_geometry import decode
    from stages.geometry.face_model import pack_face_model
    from stages.geometry.smooth import GaussianSmooth
    from stages.geometry.track import read_first_frame_points, track_points

    names, start, _ = read_first_frame_points(init)
    pack = load_pack(performer)
    rigid = named_columns(np.array(names), tuple(pack.layout.point_names[i] for i in pack.layout.rigid))
    frames = decode(clip)
    tracks = track_points(iter(frames), start, method="ncc",
                          face_model=pack_face_model(pack, names, start, rigid, pack.intrinsics))
    height, width = frames[0].shape[:2]
    points = {"xy": tracks.xy, "valid": tracks.valid, "names": np.array(names), "size": np.array([width, height])}
    return GaussianSmooth().run({"points": points}, {}, ctx)["points"]


def pose_compensate(points: Mapping[str, np.ndarray], pose: Mapping[str, np.ndarray], performer: Path,
                    ctx: Context) -> dict[str, np.ndarray]:
    """The ``compensate.pose3d`` stage's displacements."""
    return PoseCompensate().run({"points": points, "pose": pose, "pack": performer}, {}, ctx)["displacements"]


def compensations(points: Mapping[str, np.ndarray], performer: Path, ctx: Context,
                  truth: Mapping[str, np.ndarray] | None = None, pose_params: Mapping[str, Any] | None = None
                  ) -> dict[str, dict[str, np.ndarray]]:
    """Displacement bundles of ``compensate2d``, ``compensate3d`` (the ``pose.pnp`` stage with
    ``pose_params``) and, given the truth, ``compensate3d_truepose``."""
    pose = PnPPose().run({"points": points, "pack": performer}, dict(pose_params or {}), ctx)["pose"]
    out = {"compensate2d": SimilarityCompensate().run({"points": points}, {}, ctx)["displacements"],
           "compensate3d": pose_compensate(points, pose, performer, ctx)}
    if truth is not None:
        true_pose = {"R": truth["R"], "tvec": truth["tvec"], "rvec": truth["rvec"],
                     "valid": np.ones(len(truth["R"]), bool), "camera": truth["intrinsics"]}
        out["compensate3d_truepose"] = pose_compensate(points, true_pose, performer, ctx)
    return out


def chain_error(displacements: Mapping[str, np.ndarray], target: Path, pca_model: Any, ideal: np.ndarray,
                mode: str, ctx: Context) -> float:
    """Mean px distance over all points of map.expression -> propagate.hierarchical to ``ideal (T, N, 2)``."""
    mapped = ExpressionMap().run({"displacements": displacements, "pack": target}, {"mode": mode}, ctx)["points"]
    result = HierarchicalPropagation().run({"pca_model": pca_model, "points": mapped},
                                           {"stop_progress_px": 1e-3, "max_iterations": 200}, ctx)["points"]
    return float(np.linalg.norm(result["xy"] - ideal, axis=-1).mean())


def fps(work: Callable[[], Any], n_frames: int, *, repeats: int = 20) -> float:
    """Frames per second of ``work()`` over ``n_frames`` frames (best of ``repeats``)."""
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        work()
        best = min(best, time.perf_counter() - start)
    return n_frames / best


def speeds(points: Mapping[str, np.ndarray], performer: Path, ctx: Context) -> tuple[float, float]:
    """Frames per second of the 3D compensation (adaptation + frontalization) and of the 2D one."""
    pose = PnPPose().run({"points": points, "pack": performer}, {}, ctx)["pose"]
    pack = load_pack(performer)
    xy, valid, names = points["xy"], points["valid"], [str(n) for n in points["names"]]
    generic = pack.model3d[[pack.layout.index(n) for n in names]]
    rigid = named_columns(np.array(names), tuple(pack.layout.point_names[i] for i in pack.layout.rigid))
    R, t, camera = pose["R"], pose["tvec"], pack.intrinsics

    def run_3d() -> None:
        frontalize(xy, adapt_to_reference(generic, xy[0], R[0], t[0], camera), R, t, camera)

    return fps(run_3d, len(xy)), fps(lambda: compensate(xy, valid, xy[0], rigid), len(xy))


def bench_rows(fixtures: Path = Path("fixtures"), *, tracker: bool = True) -> list[dict[str, Any]]:
    """The rows listed in the module docstring, for the fixture set under ``fixtures``."""
    ctx = Context(device="cpu", files_dir=lambda port: Path("/nonexistent"))
    performer, target = fixtures / "packs" / "performer", fixtures / "packs" / "target"
    pca_model = TrainHierarchicalPCA().run({"pack": target}, {"n_components": 8, "variance_kept": 1.0}, ctx)["pca_model"]
    target_neutral = load_pack(target).neutral.points
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
                rows.append(row(f"{name}_chain_err_px_{clip}_{mode}",
                                chain_error(results[name], target, pca_model, truth["target_points"], mode, ctx), "px"))
        rows.append(row(f"chain_neutral_err_px_{clip}",
                        np.linalg.norm(target_neutral[None] - truth["target_points"], axis=-1).mean(), "px"))
        if tracker:
            clips = fixtures / "clips"
            tracked = tracker_points(clips / f"{clip}.mp4", clips / f"{clip}_track0.csv", performer, ctx)
            for name, bundle in compensations(tracked, performer, ctx, pose_params=PIPELINE_POSE).items():
                rows.append(row(f"{name}_tracked_chain_err_px_{clip}_none",
                                chain_error(bundle, target, pca_model, truth["target_points"], "none", ctx), "px"))
            pose = PnPPose().run({"points": tracked, "pack": performer}, {"points": EYES_NOSE}, ctx)["pose"]
            bundle = pose_compensate(tracked, pose, performer, ctx)
            rows.append(row(f"compensate3d_tracked_chain_err_px_{clip}_none_eyes_nose",
                            chain_error(bundle, target, pca_model, truth["target_points"], "none", ctx), "px"))
        if clip == "live":
            fps_3d, fps_2d = speeds(points, performer, ctx)
            rows += [row("compensate3d_fps_live", fps_3d, "fps"),
                     row("compensate3d_fps_ratio_vs_2d", fps_3d / fps_2d, "x")]
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
