"""Head pose by PnP (eq. 10) against known poses and cv2.solvePnP with another solver."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from runner.stage import StageError
from stages.geometry.pose import PnPPose, default_intrinsics, estimate_poses
from stages.layout import load_layout
from tests.stages.geometry.synthetic import context, pack_inputs

CAMERA = default_intrinsics((640, 480))
# hairline arc and inner eye corners of a generic head, mm (x right, y down, z away from camera)
MODEL = np.array(
    [[-45, -75, 25], [-25, -85, 10], [0, -88, 5], [25, -85, 10], [45, -75, 25], [-15, 0, 5], [15, 0, 5]], dtype=np.float64
)


def angle_deg(r1: np.ndarray, r2: np.ndarray) -> np.ndarray:
    """Rotation angle between rotation vectors ``(T, 3)``, degrees."""
    return np.degrees((Rotation.from_rotvec(r1).inv() * Rotation.from_rotvec(r2)).magnitude())


def sequence(n_frames: int, *, noise_px: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames)
    rvec = np.stack([0.25 * np.sin(t / 6.0), 0.35 * np.sin(t / 9.0 + 1.0), 0.1 * np.sin(t / 5.0)], axis=1)
    tvec = np.stack([10 * np.sin(t / 8.0), -5 + 4 * np.cos(t / 7.0), 600 + 20 * np.sin(t / 10.0)], axis=1)
    image = np.stack([cv2.projectPoints(MODEL, rvec[k], tvec[k], CAMERA, None)[0].reshape(-1, 2) for k in range(n_frames)])
    return rvec, tvec, image + rng.normal(0, noise_px, image.shape)


def test_default_intrinsics():
    np.testing.assert_allclose(default_intrinsics((320, 240)), [[320, 0, 159.5], [0, 320, 119.5], [0, 0, 1]])


def test_recovers_exact_poses():
    rvec, tvec, image = sequence(20, noise_px=0.0)
    pose = estimate_poses(image, np.ones(image.shape[:2], bool), MODEL, CAMERA)
    assert angle_deg(pose["rvec"], rvec).max() < 1e-5
    np.testing.assert_allclose(pose["tvec"], tvec, atol=1e-3)
    np.testing.assert_allclose(pose["R"], Rotation.from_rotvec(rvec).as_matrix(), atol=1e-7)
    assert pose["valid"].all() and pose["reproj_err_px"].max() < 1e-4


def test_agrees_with_opencv_sqpnp_under_noise():
    rvec, tvec, image = sequence(30, noise_px=0.3, seed=1)
    pose = estimate_poses(image, np.ones(image.shape[:2], bool), MODEL, CAMERA)
    reference = [cv2.solvePnP(MODEL, image[k], CAMERA, None, flags=cv2.SOLVEPNP_SQPNP) for k in range(30)]
    ref_r = np.array([r[1].ravel() for r in reference])
    ref_t = np.array([r[2].ravel() for r in reference])
    # both minimize the same reprojection error: they agree far better than either with the truth
    assert angle_deg(pose["rvec"], ref_r).max() < 0.2
    assert np.abs(pose["tvec"] - ref_t).max() < 0.01 * 600
    assert angle_deg(pose["rvec"], rvec).mean() < 2.0
    assert 0.05 < np.nanmean(pose["reproj_err_px"]) < 0.5


def test_frame_with_too_few_points_is_flagged_and_slerped():
    rvec, tvec, image = sequence(20, noise_px=0.0)
    valid = np.ones(image.shape[:2], bool)
    valid[9, :4] = False  # 3 valid rigid points: PnP impossible
    pose = estimate_poses(image, valid, MODEL, CAMERA)
    assert not pose["valid"][9] and pose["valid"].sum() == 19
    quat = Rotation.from_rotvec(pose["rvec"][[8, 10]]).as_quat()
    midpoint = Rotation.from_quat((quat[0] + quat[1]) / np.linalg.norm(quat[0] + quat[1]))
    assert (Rotation.from_rotvec(pose["rvec"][9]).inv() * midpoint).magnitude() < 1e-9
    np.testing.assert_allclose(pose["tvec"][9], 0.5 * (pose["tvec"][8] + pose["tvec"][10]), atol=1e-9)
    assert np.isfinite(pose["reproj_err_px"][9])


def test_ends_are_held_and_no_solvable_frame_is_an_error():
    rvec, tvec, image = sequence(10, noise_px=0.0)
    valid = np.ones(image.shape[:2], bool)
    valid[:3, 2:] = False
    pose = estimate_poses(image, valid, MODEL, CAMERA)
    assert not pose["valid"][:3].any()
    np.testing.assert_allclose(pose["rvec"][:3], np.repeat(pose["rvec"][3:4], 3, axis=0), atol=1e-12)
    with pytest.raises(StageError, match="rigid points"):
        estimate_poses(image, np.zeros_like(valid), MODEL, CAMERA)


def test_temporal_smoothing_reduces_jitter():
    rvec, tvec, image = sequence(60, noise_px=1.0, seed=2)
    valid = np.ones(image.shape[:2], bool)
    raw = estimate_poses(image, valid, MODEL, CAMERA)
    smooth = estimate_poses(image, valid, MODEL, CAMERA, smooth_sigma=2.0)
    assert angle_deg(smooth["rvec"], rvec).mean() < 0.8 * angle_deg(raw["rvec"], rvec).mean()


def test_stage_uses_the_pack_model_and_intrinsics(tmp_path):
    layout = load_layout("zhang134")
    model3d = np.zeros((layout.n_points, 3))
    model3d[list(layout.rigid)] = MODEL
    bundles = pack_inputs(layout, model3d=model3d, camera=CAMERA, size=(640, 480))
    pack = {port: bundles[port] for port in ("layout", "model3d", "camera")}
    rvec, tvec, image = sequence(8, noise_px=0.0)
    names = np.array([layout.point_names[i] for i in layout.tracked])
    xy = np.full((8, len(names), 2), 50.0)
    for k, i in enumerate(layout.rigid):
        xy[:, list(names).index(layout.point_names[i])] = image[:, k]
    points = {"xy": xy, "valid": np.ones(xy.shape[:2], bool), "names": names, "size": np.array([640, 480])}
    exact = {"adapt_model": False}
    out = PnPPose().run({"points": points, **pack}, exact, context(tmp_path))["pose"]
    assert angle_deg(out["rvec"], rvec).max() < 1e-5
    assert set(out) == {"rvec", "tvec", "R", "reproj_err_px", "valid", "camera"}
    np.testing.assert_array_equal(out["camera"], CAMERA)
    # the image-size default has the same camera here: same answer
    same = PnPPose().run({"points": points, **pack}, exact | {"intrinsics": "image"}, context(tmp_path))["pose"]
    np.testing.assert_allclose(same["rvec"], out["rvec"], atol=1e-9)
    wider = PnPPose().run({"points": points, **pack}, exact | {"focal_px": 900.0}, context(tmp_path))["pose"]
    assert np.abs(wider["tvec"][:, 2] - tvec[:, 2]).min() > 50
    relative = PnPPose().run({"points": points, **pack}, {}, context(tmp_path))["pose"]  # adapted
    np.testing.assert_allclose(relative["R"][0], np.eye(3), atol=1e-6)
    # the pack's camera belongs to 640x480 images: a clip of another size is refused
    with pytest.raises(StageError, match="intrinsics are for 640x480 images, the clip's frames are 320x240"):
        PnPPose().run({"points": points | {"size": np.array([320, 240])}, **pack}, exact, context(tmp_path))
    # what a parameter needs of pack.load's bundles and is not connected is named
    with pytest.raises(StageError, match="intrinsics=pack needs the input 'camera'"):
        PnPPose().run({"points": points, **pack, "camera": None}, exact, context(tmp_path))
    with pytest.raises(StageError, match="model=face needs the input 'geometry'"):
        PnPPose().run({"points": points, **pack}, {"model": "face"}, context(tmp_path))


def test_adapting_a_generic_model_to_the_frontal_first_frame():
    rvec, tvec, image = sequence(20, noise_px=0.0)
    rvec = rvec - rvec[0]  # frame 0 frontal: R = I
    image = np.stack([cv2.projectPoints(MODEL, rvec[k], tvec[k], CAMERA, None)[0].reshape(-1, 2) for k in range(20)])
    generic = MODEL + np.random.default_rng(3).normal(0.0, [6.0, 6.0, 1.0], MODEL.shape)  # another face
    valid = np.ones(image.shape[:2], bool)
    plain = estimate_poses(image, valid, generic, CAMERA)
    adapted = estimate_poses(image, valid, generic, CAMERA, adapt=True)
    assert adapted["reproj_err_px"][0] < 1e-6 and angle_deg(adapted["rvec"][:1], rvec[:1])[0] < 1e-6
    assert angle_deg(adapted["rvec"], rvec).mean() < 0.3 * angle_deg(plain["rvec"], rvec).mean()
    assert angle_deg(adapted["rvec"], rvec).max() < 1.0


def test_stage_points_parameter_names_unknown_points(tmp_path):
    layout = load_layout("zhang134")
    bundles = pack_inputs(layout, camera=CAMERA, size=(640, 480))
    pack = {port: bundles[port] for port in ("layout", "model3d", "camera")}
    names = np.array([layout.point_names[i] for i in layout.tracked])
    points = {"xy": np.zeros((2, len(names), 2)), "valid": np.ones((2, len(names)), bool), "names": names}
    with pytest.raises(StageError, match="forehead_9"):
        PnPPose().run({"points": points, **pack}, {"points": ["eye_l_0", "forehead_9"]}, context(tmp_path))
