"""compensate.rigid3d: 3D similarity compensation against known rotations (scipy as the reference)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stages.geometry.rotation import ypr_yxz
from stages.geometry.rigid3d import (
    choose_reference,
    compensate_rigid3d,
    expressiveness,
    head_angle_deg,
    similarity_3d,
)


def _head(n=40, seed=0):
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-60, 60, (n, 2)), rng.uniform(-30, 30, n)] + [250, 250, 500]


def test_similarity_3d_recovers_a_known_transform():
    src = _head()
    R = Rotation.from_euler("YXZ", [20, -10, 5], degrees=True).as_matrix()
    dst = 1.3 * src @ R.T + [4, -7, 11]
    s, R_est, t = similarity_3d(src, dst, np.ones(len(src)))
    assert s == pytest.approx(1.3, abs=1e-9)
    np.testing.assert_allclose(R_est, R, atol=1e-9)
    np.testing.assert_allclose(t, [4, -7, 11], atol=1e-6)


def test_compensation_undoes_head_rotation_and_keeps_expression():
    ref = _head()
    rigid = np.arange(20)
    expression = np.zeros_like(ref)
    expression[30:, 1] = 6.0  # non-rigid points move down 6 px (a mouth opening)
    angles = np.array([[0, 0, 0], [15, 5, -3], [-20, -8, 6]], float)
    frames = []
    for k, ypr in enumerate(angles):
        R = Rotation.from_euler("YXZ", ypr, degrees=True).as_matrix()
        centre = ref.mean(0)
        moved = (ref + (expression if k else 0) - centre) @ R.T + centre + [3 * k, -2 * k, 0]
        frames.append(moved)
    xyz = np.stack(frames)
    fit = compensate_rigid3d(xyz, np.ones(xyz.shape[:2], bool), 0, rigid)
    np.testing.assert_allclose(fit["d"][0], 0, atol=1e-9)
    for k in (1, 2):
        np.testing.assert_allclose(fit["d"][k], expression[:, :2], atol=1e-6)
    np.testing.assert_allclose(ypr_yxz(fit["R"]), angles, atol=1e-6)
    assert fit["frame_valid"].all()


def test_frames_without_rigid_points_are_held_and_flagged():
    ref = _head()
    xyz = np.stack([ref, ref + [1, 0, 0], ref + [2, 0, 0]])
    valid = np.ones(xyz.shape[:2], bool)
    valid[1, :] = False
    fit = compensate_rigid3d(xyz, valid, 0, np.arange(10))
    assert fit["frame_valid"].tolist() == [True, False, True]
    np.testing.assert_allclose(fit["t"][1], fit["t"][0])  # held from the nearest solved frame


def test_choose_reference_prefers_frontal_neutral_frames():
    names = np.array(["_neutral", "eyeLookInLeft", "jawOpen", "browInnerUp"])
    shapes = np.array(
        [
            [0.9, 0.0, 0.6, 0.1],  # mouth open
            [0.9, 0.9, 0.0, 0.0],  # gaze only: counts as neutral
            [0.9, 0.0, 0.0, 0.05],  # neutral but turned 30 degrees
            [0.9, 0.0, 0.0, 0.0],
        ]
    )  # invalid frame
    assert expressiveness(shapes, names).tolist() == pytest.approx([0.7, 0.0, 0.05, 0.0])
    matrix = np.repeat(np.eye(4)[None], 4, axis=0)
    matrix[2, :3, :3] = Rotation.from_euler("Y", 30, degrees=True).as_matrix()
    valid = np.array([True, True, True, False])
    closed = np.zeros(4)
    assert choose_reference(shapes, names, matrix, closed, valid, search_frames=10) == 1
    assert choose_reference(shapes, names, matrix, closed, valid, search_frames=1) == 0
    lips_apart = np.array([0.2, 0.2, 0.0, 0.0])  # gaps the blendshapes missed
    assert choose_reference(shapes, names, matrix, lips_apart, valid, search_frames=10) == 2
    np.testing.assert_allclose(head_angle_deg(2.0 * matrix[:, :3, :3]), [0, 0, 30, 0], atol=1e-4)


def _lower(ref, names):
    from stages.geometry.rigid3d import RIGID_POINTS

    return (ref[:, 1] > 200) & ~np.isin(names, RIGID_POINTS)


def _mediapipe_matrix(R, scale=1.7):
    """A facial transformation matrix ``(4, 4)`` in MediaPipe's axes (y up, z towards the viewer)
    of a head rotation ``R`` in the pipeline's (y down, z away), scaled as MediaPipe's are."""
    F = np.diag([1.0, -1.0, -1.0])
    M = np.eye(4)
    M[:3, :3] = scale * F @ R @ F
    return M


def _bundles(n_frames=6, landmarker_yaw_per_frame=3.0):
    """Points and landmarks bundles of a known head: frame k turned by 3k degrees of yaw; the
    non-rigid points below y = 200 moved down by 2k px; frame 4 has no face. The landmarker's
    matrices turn by ``landmarker_yaw_per_frame`` degrees a frame."""
    from stages.layout import load_layout

    names = np.array(load_layout("zhang134").point_names)
    rng = np.random.default_rng(1)
    ref = np.c_[rng.uniform(100, 300, (len(names), 2)), rng.uniform(-40, 40, len(names))]
    centre = ref.mean(0)
    xyz, shapes = [], np.zeros((n_frames, 3), np.float32)
    for k in range(n_frames):
        R = Rotation.from_euler("Y", 3 * k, degrees=True).as_matrix()
        moved = ref.copy()
        moved[_lower(ref, names), 1] += 2 * k
        xyz.append((moved - centre) @ R.T + centre)
    xyz = np.stack(xyz)
    face = np.ones(n_frames, bool)
    face[4] = False
    xyz[4] = np.nan
    valid = np.repeat(face[:, None], len(names), axis=1)
    points = {"xy": xyz[..., :2], "z": xyz[..., 2], "valid": valid, "names": names}
    marks = {
        "valid": face,
        "blendshapes": shapes,
        "blendshape_names": np.array(["_neutral", "jawOpen", "browInnerUp"]),
        "matrix": np.stack(
            [
                _mediapipe_matrix(Rotation.from_euler("Y", landmarker_yaw_per_frame * k, degrees=True).as_matrix())
                for k in range(n_frames)
            ]
        ),
    }
    marks["matrix"][4] = np.eye(4)  # no face
    return points, marks, ref, names


@pytest.mark.parametrize("pose_rotation", ["landmarker", "points"])
def test_stage_holds_frames_without_a_face_and_reports_the_reference(pose_rotation):
    from runner.stage import Context
    from stages.geometry.rigid3d import CompensateRigid3D

    points, marks, ref, names = _bundles()
    stage = CompensateRigid3D()
    # random points, not a face: their "lips" are not closed (test_close_reference_lips_* below)
    params = {p.name: p.default for p in stage.params} | {"neutral_frame": 0, "close_lips": False, "pose_rotation": pose_rotation}
    out = stage.run({"points": points, "landmarks": marks}, params, Context(device="cpu", files_dir=None))
    d = out["displacements"]
    assert int(d["neutral_frame"]) == 0 and d["held"].tolist() == [False] * 4 + [True, False]
    np.testing.assert_allclose(d["d"][4], d["d"][3])  # held from frame 3 (nearest; ties go earlier)
    assert d["valid"][4].all() and not out["pose"]["valid"][4]
    lower = _lower(ref, names)
    np.testing.assert_allclose(d["d"][5][lower, 1], 10.0, atol=1e-6)
    np.testing.assert_allclose(out["pose"]["ypr_deg"][5], [15, 0, 0], atol=1e-6)


def test_the_pose_takes_the_landmarkers_rotation_and_keeps_the_fitted_path_of_the_face():
    """The landmarker reads half the turn the points show: the pose reports the landmarker's
    rotation, the rigid points' centroid still goes where the points put it, and the
    displacements (the expression) are those of the fit, whichever rotation the pose takes."""
    from runner.stage import Context
    from stages.geometry.rigid3d import RIGID_POINTS, CompensateRigid3D

    points, marks, ref, names = _bundles(landmarker_yaw_per_frame=1.5)
    stage = CompensateRigid3D()
    base = {p.name: p.default for p in stage.params} | {"neutral_frame": 0, "close_lips": False}
    ours = stage.run({"points": points, "landmarks": marks}, base, Context(device="cpu", files_dir=None))
    fitted = stage.run(
        {"points": points, "landmarks": marks}, base | {"pose_rotation": "points"}, Context(device="cpu", files_dir=None)
    )
    np.testing.assert_allclose(ours["pose"]["ypr_deg"][5], [7.5, 0, 0], atol=1e-6)
    np.testing.assert_allclose(fitted["pose"]["ypr_deg"][5], [15, 0, 0], atol=1e-6)
    rigid = np.isin(names, RIGID_POINTS)
    centre = np.c_[points["xy"][0], points["z"][0]][rigid].mean(axis=0)
    for out in (ours, fitted):
        pose = out["pose"]
        moved = pose["scale"][:, None] * np.einsum("tij,j->ti", pose["R"], centre) + pose["tvec"]
        truth = np.c_[points["xy"][5], points["z"][5]][rigid].mean(axis=0)  # frame 5: a rigid turn of frame 0
        np.testing.assert_allclose(moved[5], truth, atol=1e-6)
    np.testing.assert_allclose(ours["displacements"]["d"], fitted["displacements"]["d"])


def test_stage_refuses_points_without_depth():
    from runner.stage import Context, StageError
    from stages.geometry.rigid3d import CompensateRigid3D

    points, marks, _, _ = _bundles()
    del points["z"]
    stage = CompensateRigid3D()
    with pytest.raises(StageError, match="no depth"):
        stage.run(
            {"points": points, "landmarks": marks},
            {p.name: p.default for p in stage.params},
            Context(device="cpu", files_dir=None),
        )


def _face_with_open_lips(gap_px, roll_deg=0.0):
    """The fixture target's neutral (zhang134 names) with its lips exactly closed, and a copy with
    the lower inner lips and lower teeth moved down the face by ``gap_px``; both turned by
    ``roll_deg`` in the image."""
    from stages.actor_pack import load_pack

    pack = load_pack("fixtures/packs/target")
    names = np.array(pack.layout.point_names)
    closed = np.asarray(pack.neutral.points, np.float64)
    column = {str(n): i for i, n in enumerate(names)}
    eye_line = closed[column["eye_r_6"]] - closed[column["eye_l_6"]]
    level = Rotation.from_euler("z", -np.arctan2(eye_line[1], eye_line[0])).as_matrix()[:2, :2]
    closed = (closed - closed.mean(axis=0)) @ level.T + 256.0  # eye line horizontal
    for k in range(4):  # lips exactly closed: each pair's lower lip and teeth on the upper lip's line
        upper = column[f"mouth_inner_{k + 1}"]
        for name in (f"mouth_inner_{9 - k}", f"teeth_upper_{k}", f"teeth_lower_{k}"):
            closed[column[name], 1] = closed[upper, 1]
    opened = closed.copy()
    lower = np.isin(names, [f"mouth_inner_{k}" for k in (6, 7, 8, 9)] + [f"teeth_lower_{k}" for k in range(4)])
    opened[lower, 1] += gap_px
    turn = Rotation.from_euler("z", roll_deg, degrees=True).as_matrix()[:2, :2]
    centre = closed.mean(axis=0)
    return (closed - centre) @ turn.T + centre, (opened - centre) @ turn.T + centre, names


@pytest.mark.parametrize("roll", [0.0, 25.0])
def test_close_reference_lips_makes_the_opening_count_from_closed_lips(roll):
    """Regression (robustness campaign): a reference frame with the lips apart made every frame
    where the performer closes them push the target's lips through each other (clamped, so the
    target's mouth opening lost 10-19 % of its amplitude). From the closed reference the
    displacements carry the whole opening; the compensated geometry itself is unchanged."""
    from stages.geometry.rigid3d import close_reference_lips
    from stages.geometry.signals import expression_signals

    face_closed, reference, names = _face_with_open_lips(12.0, roll)
    frames = np.stack([face_closed, reference, _face_with_open_lips(30.0, roll)[1]])  # closed, as ref, wider
    d = frames - reference[None]
    closed, d_closed, gap = close_reference_lips(reference, d, names)
    assert gap == pytest.approx(12.0)
    np.testing.assert_allclose(closed[None] + d_closed, frames, atol=1e-9)
    opening = expression_signals(np.concatenate([closed[None], frames]), names)["mouth_open"]
    assert opening[0] == pytest.approx(0.0, abs=1e-9)  # the closed reference: lips meet, on the face's axis
    eye = expression_signals(frames, names)["eye_distance_px"][0]
    np.testing.assert_allclose(opening[1:] * eye, [0.0, 12.0, 30.0], atol=1e-9)
    # mapped onto a closed target with no scaling: target opening = performer's, nothing to clamp
    target = face_closed[None] + d_closed
    np.testing.assert_allclose(expression_signals(target, names)["mouth_open"] * eye, [0.0, 12.0, 30.0], atol=1e-9)
    # the points away from the mouth keep their displacements
    mouth = np.array([str(n).startswith(("mouth_inner", "teeth")) for n in names])
    np.testing.assert_array_equal(d_closed[:, ~mouth], d[:, ~mouth])


def test_close_reference_lips_leaves_a_closed_reference_alone():
    from stages.geometry.rigid3d import close_reference_lips

    face_closed, _, names = _face_with_open_lips(0.0)
    d = np.random.default_rng(0).normal(size=(3, len(names), 2))
    closed, d_closed, gap = close_reference_lips(face_closed, d, names)
    assert gap == 0.0
    np.testing.assert_array_equal(closed, face_closed)
    np.testing.assert_array_equal(d_closed, d)


@pytest.mark.parametrize("close_lips", [True, False])
def test_stage_takes_displacements_from_the_reference_with_closed_lips(close_lips):
    """The stage's wiring of close_reference_lips (parameter close_lips, default true): the
    displacements it hands to the mapping start from closed lips; off, from the reference."""
    from runner.stage import Context
    from stages.geometry.rigid3d import CompensateRigid3D
    from stages.geometry.signals import expression_signals

    face_closed, reference, names = _face_with_open_lips(12.0)
    xy = np.stack([reference, face_closed, _face_with_open_lips(30.0)[1]])
    n = len(xy)
    points = {"xy": xy, "z": np.zeros(xy.shape[:2]), "valid": np.ones(xy.shape[:2], bool), "names": names}
    marks = {
        "valid": np.ones(n, bool),
        "blendshapes": np.zeros((n, 1), np.float32),
        "blendshape_names": np.array(["_neutral"]),
        "matrix": np.repeat(np.eye(4)[None], n, axis=0),
    }
    stage = CompensateRigid3D()
    params = {p.name: p.default for p in stage.params} | {"neutral_frame": 0, "close_lips": close_lips}
    assert next(p for p in stage.params if p.name == "close_lips").default is True
    out = stage.run({"points": points, "landmarks": marks}, params, Context(device="cpu", files_dir=None))["displacements"]
    np.testing.assert_allclose(out["neutral"][None] + out["d"], xy, atol=1e-6)
    eye = expression_signals(xy, names)["eye_distance_px"][0]
    opening = expression_signals(out["neutral"][None], names)["mouth_open"][0] * eye
    assert opening == pytest.approx(0.0 if close_lips else 12.0, abs=1e-6)


@pytest.mark.parametrize(
    "neutral_frame, advice",
    [
        (
            5,
            "the reference frame 5 set by neutral_frame is not a frontal neutral face (head turned 15.0 deg, expressiveness "
            "0.00); neutral_frame=-1 estimates the neutral from the whole clip",
        ),
        (-1, "the most frontal frame of the clip, 0, is turned 15.0 deg: displacements are measured in a turned head frame"),
    ],
)
def test_the_reference_warning_advises_what_was_not_done(caplog, neutral_frame, advice):
    """Frame 5 is turned 15 degrees (more than warn_angle_deg): named by the user, the warning
    does not tell them to set neutral_frame but that the estimate exists; with the neutral
    estimated (every frame turned alike), it says the head frame is turned and advises nothing
    that was done."""
    import logging

    from runner.stage import Context
    from stages.geometry.rigid3d import CompensateRigid3D

    points, marks, _, _ = _bundles()
    marks["matrix"][5, :3, :3] = Rotation.from_euler("Y", 15, degrees=True).as_matrix()  # as the points turn
    stage = CompensateRigid3D()
    params = {p.name: p.default for p in stage.params} | {"neutral_frame": neutral_frame, "close_lips": False}
    if neutral_frame < 0:
        for key in ("valid", "blendshapes", "matrix"):
            marks[key] = marks[key][5:]
        points = {k: (v[5:] if k != "names" else v) for k, v in points.items()}
    with caplog.at_level(logging.WARNING):
        stage.run({"points": points, "landmarks": marks}, params, Context(device="cpu", files_dir=None))
    warned = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING and "turned 15.0 deg" in r.getMessage()]
    assert len(warned) == 1 and warned[0].endswith(advice) and "set neutral_frame=N" not in warned[0]


def test_stage_holds_an_occluded_region_from_the_frames_around_it():
    """The non-rigid points below y = 200 move down 2 px a frame; an ``occlusion`` bundle hides
    them ("mouth") in frames 1-2: their displacements there are the line from frame 0 to frame 3,
    whatever the landmarks guessed under the hand (here: 50 px off), and the other points keep
    theirs; the occluded frames are flagged."""
    from runner.stage import Context
    from stages.geometry.rigid3d import CompensateRigid3D

    points, marks, ref, names = _bundles()
    lower = _lower(ref, names)
    points["xy"][1:3][:, lower] += 50.0  # what a landmarker guesses under a hand
    hidden = np.zeros((6, 1), bool)
    hidden[1:3, 0] = True
    occlusion = {
        "regions": np.array(["mouth"]),
        "occluded": hidden,
        "region_points": lower[None],
        "names": names,
        "valid": np.ones(6, bool),
        "score": np.where(hidden, 0.0, 1.0),
    }
    stage = CompensateRigid3D()
    params = {p.name: p.default for p in stage.params} | {"neutral_frame": 0, "close_lips": False}
    ctx = Context(device="cpu", files_dir=None)
    held = stage.run({"points": points, "landmarks": marks, "occlusion": occlusion}, params, ctx)["displacements"]
    seen = stage.run({"points": points, "landmarks": marks}, params, ctx)["displacements"]
    for t in (1, 2):
        np.testing.assert_allclose(
            held["d"][t][lower], seen["d"][0][lower] + t / 3 * (seen["d"][3][lower] - seen["d"][0][lower]), atol=1e-9
        )
    np.testing.assert_allclose(held["d"][:, ~lower], seen["d"][:, ~lower])
    np.testing.assert_array_equal(held["occluded"], [False, True, True, False, False, False])
    assert np.abs(seen["d"][1][lower, 1] - 2.0).min() > 40  # without the bundle the guess is taken
