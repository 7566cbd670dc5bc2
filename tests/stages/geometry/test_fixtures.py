"""The geometry stages on the fixture clips (scripts/make_fixtures.py) against their ground truth.

Tolerances sit a little above what the current code measures (scripts/bench_geometry.py prints
the figures), so that a regression breaks them; see docs/fixtures.md for the clips.
"""

from __future__ import annotations

import os
from pathlib import Path

import av
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stages.actor_pack import load_pack
from stages.geometry.compensate import SimilarityCompensate
from stages.geometry.pose import PnPPose
from stages.geometry.smooth import GaussianSmooth
from stages.geometry.track import CorrelationTrack
from stages.layout import load_layout
from stages.pack.bundles import pack_to_bundles
from tests.stages.geometry.synthetic import MemoryStream, context

ROOT = Path(os.environ.get("EXPRESSION_FIXTURES", Path(__file__).resolve().parents[3] / "fixtures"))


def decode(path: Path) -> np.ndarray:
    with av.open(str(path)) as container:
        return np.stack([frame.to_ndarray(format="rgb24") for frame in container.decode(video=0)])


@pytest.fixture(scope="module", params=["calm", "live"])
def clip(request):
    """Tracked points of one clip through the stage chain track -> smooth -> compensate -> pose."""
    kind = request.param
    ctx = context(Path("/nonexistent"))
    frames = MemoryStream(decode(ROOT / "clips" / f"{kind}.mp4"), chunk=16)
    truth = dict(np.load(ROOT / "clips" / f"{kind}_truth.npz", allow_pickle=False))
    pack = pack_to_bundles(load_pack(ROOT / "packs" / "performer"))
    face_model = {port: pack[port] for port in ("model3d", "geometry", "camera")}
    pose_inputs = {port: pack[port] for port in ("layout", "model3d", "camera", "geometry")}
    init = ROOT / "clips" / f"{kind}_track0.csv"
    tracked = {
        "2d_only": CorrelationTrack().run({"frames": frames, "init": init}, {}, ctx)["points"],
        "face_model": CorrelationTrack().run({"frames": frames, "init": init, **face_model}, {}, ctx)["points"],
    }
    smoothed = GaussianSmooth().run({"points": tracked["face_model"]}, {}, ctx)["points"]
    compensated = SimilarityCompensate().run({"points": smoothed}, {}, ctx)
    pose = {
        "rigid": PnPPose().run({"points": smoothed, **pose_inputs}, {}, ctx)["pose"],
        "eyes_nose": PnPPose().run({"points": smoothed, **pose_inputs}, {"points": EYES_NOSE}, ctx)["pose"],
        "face": PnPPose().run({"points": smoothed, **pose_inputs}, {"model": "face"}, ctx)["pose"],
    }
    return kind, truth, tracked, smoothed, compensated, pose


def truth_of(truth: dict, names: np.ndarray, key: str = "points") -> np.ndarray:
    index = {n: i for i, n in enumerate(truth["point_names"])}
    return truth[key][:, [index[str(n)] for n in names]]


EYES_NOSE = ["eye_l_0", "eye_r_0", "eye_l_6", "eye_r_6", "nose_tip", "nose_ala_l", "nose_ala_r", "nose_base"]
# measured 0.422, 1.696 (2D only) and 0.277, 0.983 (with the performer pack's face model)
TRACK_MEAN_PX = {("calm", "2d_only"): 0.45, ("live", "2d_only"): 1.75, ("calm", "face_model"): 0.30, ("live", "face_model"): 1.02}
# Jitter: the mean second difference of the tracking error (px/frame^2), a high-pass measure that
# slow drift and the smoother's lag barely touch. Smoothed / raw, face-model tracks, measured 0.360
# (calm) and 0.820 (live).
JITTER_RATIO = {"calm": 0.45, "live": 0.9}
# Lag: the mean first difference of the tracking error, smoothed / raw, measured 0.853 and 1.224:
# on the live clip's fast head motion the smoother's lag adds more slow error than it removes (a
# bound on the damage, not a gain).
LAG_RATIO = {"calm": 0.95, "live": 1.25}
# mean rotation error, deg, all from the smoothed tracks; measured calm 0.226, 0.322, 0.291 and
# live 1.096, 1.725, 1.171 (rigid PnP, eyes + nose PnP, face model). Before smoothing kept the
# first frame in place, PnP's model adapted to a shifted neutral gave 3.10 and 3.94 on live.
# The calm figures are a few hundredths of a degree and move with sub-pixel changes of the
# clip: before the generator's mouth mesh stopped pulling the chin skin with the upper lip
# (needed for wide openings) they were 0.165, 0.322, 0.210, and with the same clip but other
# performer packs (captured jaw openings scaled 0.5 / 0.6 / 1.0) rigid PnP gives 0.226 / 0.218 /
# 0.277 and the face model 0.291 / 0.232 / 0.230
POSE_DEG = {
    ("calm", "rigid"): 0.27,
    ("calm", "eyes_nose"): 0.36,
    ("calm", "face"): 0.35,
    ("live", "rigid"): 1.3,
    ("live", "eyes_nose"): 1.85,
    ("live", "face"): 1.4,
}


@pytest.mark.parametrize("tracker", ["2d_only", "face_model"])
def test_tracking_error(clip, tracker):
    kind, truth, tracks, *_ = clip
    tracked = tracks[tracker]
    error = np.linalg.norm(tracked["xy"] - truth_of(truth, tracked["names"]), axis=2)
    visible = truth_of(truth, tracked["names"], "visible")
    assert error[0].max() < 1e-6
    assert error[1:][visible[1:]].mean() < TRACK_MEAN_PX[kind, tracker]
    assert tracked["valid"][1:][visible[1:]].mean() > 0.9


def error_change(xy: np.ndarray, gt: np.ndarray, order: int) -> float:
    """Mean norm of the ``order``-th frame difference of the tracking error ``xy - gt``, px."""
    return float(np.linalg.norm(np.diff(xy - gt, n=order, axis=0), axis=2).mean())


def test_smoothing_reduces_jitter(clip):
    kind, truth, tracks, smoothed, *_ = clip
    tracked = tracks["face_model"]
    gt = truth_of(truth, tracked["names"])
    assert error_change(smoothed["xy"], gt, 2) < JITTER_RATIO[kind] * error_change(tracked["xy"], gt, 2)


def test_smoothing_lag_stays_bounded(clip):
    kind, truth, tracks, smoothed, *_ = clip
    tracked = tracks["face_model"]
    gt = truth_of(truth, tracked["names"])
    assert error_change(smoothed["xy"], gt, 1) < LAG_RATIO[kind] * error_change(tracked["xy"], gt, 1)


@pytest.mark.parametrize("points", ["rigid", "eyes_nose", "face"])
def test_pose_error(clip, points):
    kind, truth, _, _, _, poses = clip
    pose = poses[points]
    angle = np.degrees((Rotation.from_matrix(pose["R"]).inv() * Rotation.from_matrix(truth["R"])).magnitude())
    assert angle.mean() < POSE_DEG[kind, points]
    assert pose["valid"].all() and angle[0] < 1e-6


def test_compensation_on_the_true_points_matches_the_generator():
    """Eq. 9 on the true rigid points reproduces the generator's own similarity."""
    layout = load_layout("zhang134")
    truth = dict(np.load(ROOT / "clips" / "live_truth.npz", allow_pickle=False))
    names = np.array(layout.point_names)
    points = {"xy": truth["points"], "valid": np.ones(truth["points"].shape[:2], bool), "names": names}
    neutral = {"xy": truth["neutral_points"][None], "valid": np.ones((1, len(names)), bool), "names": names}
    out = SimilarityCompensate().run({"points": points, "neutral": neutral}, {}, context(Path("/nonexistent")))
    np.testing.assert_allclose(out["similarity"]["params"], truth["similarity"], atol=1e-9)


def test_pose_with_the_performers_own_model_is_exact():
    layout = load_layout("zhang134")
    truth = dict(np.load(ROOT / "clips" / "live_truth.npz", allow_pickle=False))
    pack = load_pack(ROOT / "packs" / "performer")
    from stages.geometry.pose import estimate_poses

    rigid = list(layout.rigid)
    pose = estimate_poses(
        truth["points"][:, rigid], np.ones((len(truth["R"]), len(rigid)), bool), truth["points3d"][0][rigid], pack.intrinsics
    )
    angle = np.degrees((Rotation.from_matrix(pose["R"]).inv() * Rotation.from_matrix(truth["R"])).magnitude())
    assert angle.max() < 1e-3


def test_mapping_onto_the_target_pack():
    """compensate -> map on the calm clip, from the true and from the tracked points, against the
    generator's ideal mapping (the target's own face with the same expression controls)."""
    from stages.geometry.mapping import ExpressionMap

    ctx = context(Path("/nonexistent"))
    truth = dict(np.load(ROOT / "clips" / "calm_truth.npz", allow_pickle=False))
    frames = MemoryStream(decode(ROOT / "clips" / "calm.mp4"), chunk=16)
    tracked = CorrelationTrack().run({"frames": frames, "init": ROOT / "clips" / "calm_track0.csv"}, {}, ctx)["points"]
    smoothed = GaussianSmooth().run({"points": tracked}, {}, ctx)["points"]
    exact = dict(smoothed, xy=truth_of(truth, smoothed["names"]), valid=np.ones_like(smoothed["valid"]))
    columns = list(truth["tracked"])
    target = pack_to_bundles(load_pack(ROOT / "packs" / "target"))
    errors = {}
    for label, points in (("tracked", smoothed), ("exact", exact)):
        displacements = SimilarityCompensate().run({"points": points}, {}, ctx)["displacements"]
        mapped = ExpressionMap().run(
            {"displacements": displacements, "layout": target["layout"], "geometry": target["geometry"]}, {}, ctx
        )["points"]
        errors[label] = np.linalg.norm(mapped["xy"][:, columns] - truth["target_points"][:, columns], axis=2).mean()
        assert mapped["valid"][:, columns].mean() > 0.95
    neutral_only = np.linalg.norm(mapped["xy"][:1, columns] - truth["target_points"][:, columns], axis=2).mean()
    # mapping the true motion gets closer to the ideal than leaving the target neutral; tracking
    # errors, magnified by the target's larger face, then cost a little more (measured 1.10 px)
    assert errors["exact"] < 0.8 * neutral_only
    assert errors["tracked"] < 1.2


def test_tracker_refuses_a_pack_for_another_frame_size():
    """The face model needs the pack's intrinsics: a pack made for other images is a clear error."""
    from runner.stage import StageError

    frames = MemoryStream(decode(ROOT / "clips" / "live.mp4")[:3], chunk=16)
    target = pack_to_bundles(load_pack(ROOT / "packs" / "target"))
    inputs = {
        "frames": frames,
        "init": ROOT / "clips" / "live_track0.csv",
        **{port: target[port] for port in ("model3d", "geometry", "camera")},
    }
    with pytest.raises(StageError, match="intrinsics are for 240x320 images, the clip's frames are 320x240"):
        CorrelationTrack().run(inputs, {}, context(Path("/nonexistent")))
    del inputs["camera"]
    with pytest.raises(StageError, match="needs the inputs model3d, geometry, camera together .* got only model3d, geometry"):
        CorrelationTrack().run(inputs, {}, context(Path("/nonexistent")))
