"""The face model fit (pose + expression, stages/geometry/face_model.py) against known poses and
coefficients and against cv2.solvePnP."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stages.geometry.face_model import FaceFit, FaceModel, build_face_model, fit_face_model
from stages.geometry.pose import default_intrinsics, estimate_face_poses

CAMERA = default_intrinsics((640, 480))
RNG = np.random.default_rng(3)
# a face-sized cloud of 30 points, mm, head frame (x right, y down, z away from the camera)
SHAPE = np.column_stack([RNG.uniform(-60, 60, 30), RNG.uniform(-90, 70, 30), RNG.uniform(-25, 30, 30)])
T0 = np.array([5.0, -10.0, 600.0])


def model_with(components: int) -> FaceModel:
    basis = np.linalg.qr(RNG.normal(size=(SHAPE.size, max(components, 1))))[0][:, :components]
    return FaceModel(SHAPE, basis.reshape(len(SHAPE), 3, components), np.full(components, 8.0), T0, CAMERA)


def start_of(model: FaceModel) -> FaceFit:
    m = model.basis.shape[2]
    return FaceFit(np.eye(3), model.t0.copy(), np.zeros(m), model.project(np.eye(3), model.t0, np.zeros(m)))


def angle_deg(r1: np.ndarray, r2: np.ndarray) -> float:
    return float(np.degrees((Rotation.from_matrix(r1).inv() * Rotation.from_matrix(r2)).magnitude()))


def test_projection_is_opencv_project_points():
    model = model_with(3)
    rvec, t, c = np.array([0.2, -0.3, 0.1]), np.array([10.0, 4.0, 650.0]), np.array([5.0, -3.0, 2.0])
    expected = cv2.projectPoints(SHAPE + model.basis @ c, rvec, t, CAMERA, None)[0].reshape(-1, 2)
    np.testing.assert_allclose(model.project(cv2.Rodrigues(rvec)[0], t, c), expected, atol=1e-9)


def test_fit_recovers_pose_and_expression_exactly():
    model = model_with(4)
    R = Rotation.from_euler("yxz", [25, -12, 8], degrees=True).as_matrix()
    t, c = np.array([-20.0, 15.0, 640.0]), np.array([6.0, -4.0, 3.0, -2.0])
    observed = model.project(R, t, c)
    fit = fit_face_model(
        model, observed, np.broadcast_to(np.eye(2), (len(SHAPE), 2, 2)), start_of(model), ridge=0.0, iterations=15
    )
    assert angle_deg(fit.R, R) < 1e-6
    np.testing.assert_allclose(fit.t, t, atol=1e-5)
    np.testing.assert_allclose(fit.c, c, atol=1e-5)
    np.testing.assert_allclose(fit.xy, observed, atol=1e-6)


def test_without_expression_the_fit_is_pnp_and_agrees_with_opencv_under_noise():
    """No expression components: the fit is PnP (eq. 10); it agrees with cv2.solvePnP's
    Levenberg-Marquardt on noisy points (same least-squares problem, another solver)."""
    model = model_with(0)
    R = Rotation.from_euler("yxz", [-18, 9, -5], degrees=True).as_matrix()
    t = np.array([12.0, -6.0, 580.0])
    observed = model.project(R, t, np.zeros(0)) + RNG.normal(0.0, 0.7, (len(SHAPE), 2))
    fit = fit_face_model(
        model, observed, np.broadcast_to(np.eye(2), (len(SHAPE), 2, 2)), start_of(model), huber_px=1e6, iterations=15
    )
    ok, rvec, tvec = cv2.solvePnP(SHAPE, observed, CAMERA, None, flags=cv2.SOLVEPNP_ITERATIVE)
    assert ok
    assert angle_deg(fit.R, cv2.Rodrigues(rvec)[0]) < 1e-4
    np.testing.assert_allclose(fit.t, tvec.ravel(), atol=1e-3)


def test_robust_fit_bounds_an_outliers_pull_and_weights_follow_the_information():
    model = model_with(2)
    R = Rotation.from_euler("y", 15, degrees=True).as_matrix()
    t, c = np.array([0.0, 0.0, 620.0]), np.array([4.0, -5.0])
    observed = model.project(R, t, c)
    bad = observed.copy()
    bad[3] += (25.0, -18.0)  # a lost point
    unit = np.broadcast_to(np.eye(2), (len(SHAPE), 2, 2))
    fit = fit_face_model(model, bad, unit, start_of(model), ridge=0.0, iterations=20)
    plain = fit_face_model(model, bad, unit, start_of(model), ridge=0.0, huber_px=1e6, iterations=20)
    assert angle_deg(fit.R, R) < 0.1 and angle_deg(fit.R, R) < 0.2 * angle_deg(plain.R, R)  # Huber: bounded pull
    assert np.linalg.norm(fit.xy[3] - observed[3]) < 1.0
    # zero information on the lost point: exact again
    information = unit.copy()
    information[3] = 0.0
    fit = fit_face_model(model, bad, information, start_of(model), ridge=0.0, iterations=15)
    assert angle_deg(fit.R, R) < 1e-6


def test_build_lifts_the_captured_expressions_at_the_generic_depth():
    """The basis spans the captured displacements: a captured geometry (frontal, R = I) is
    reproduced exactly by the model at the first frame's pose."""
    rigid = np.arange(6)
    first = CAMERA[:2, :2] @ (SHAPE[:, :2] / (SHAPE[:, 2:] + T0[2])).T + CAMERA[:2, 2:]  # frontal neutral
    first = first.T
    captured = first[None] + RNG.normal(0.0, 3.0, (5, len(SHAPE), 2))
    model = build_face_model(SHAPE, first, rigid, CAMERA, first, captured, components=5)
    np.testing.assert_allclose(model.project(np.eye(3), model.t0, np.zeros(5)), first, atol=1e-6)
    np.testing.assert_allclose(model.neutral[:, 2], SHAPE[:, 2], atol=1e-9)  # generic depths kept
    for geometry in captured:
        fit = fit_face_model(
            model, geometry, np.broadcast_to(np.eye(2), (len(SHAPE), 2, 2)), start_of(model), ridge=0.0, iterations=10
        )
        np.testing.assert_allclose(fit.xy, geometry, atol=1e-4)
        assert angle_deg(fit.R, np.eye(3)) < 1e-4


def test_estimate_face_poses_interpolates_frames_with_too_few_points():
    model = model_with(0)
    angles = np.linspace(0, 20, 6)
    rotations = Rotation.from_euler("y", angles[:, None], degrees=True).as_matrix()
    image = np.stack([model.project(r, T0, np.zeros(0)) for r in rotations])
    valid = np.ones(image.shape[:2], bool)
    valid[3, 3:] = False  # 3 points left in frame 3
    pose = estimate_face_poses(image, valid, model)
    assert pose["valid"].tolist() == [True, True, True, False, True, True]
    errors = [angle_deg(pose["R"][k], rotations[k]) for k in range(6)]
    assert max(errors[k] for k in (0, 1, 2, 4, 5)) < 1e-5
    assert errors[3] < 1e-3  # slerp between 12 and 20 degrees about y: exact
    assert set(pose) == {"rvec", "tvec", "R", "reproj_err_px", "valid"}
    with pytest.raises(Exception, match="no frame has 4 valid points"):
        estimate_face_poses(image, np.zeros_like(valid), model)


def test_tracker_weighs_each_match_by_its_running_distance_to_the_model():
    """NCCTracker.with_model: a point whose matches keep off the fitted model loses weight against
    it, one whose matches keep on it gains (up to 4x); the fused position is the closed form
    (q H m + mu p) / (q H + mu) with q from the running mean of squared distances."""
    from stages.geometry.ncc_tracker import NCCTracker
    from stages.geometry.tracker_options import TrackerOptions

    model = model_with(2)
    options = TrackerOptions(model_prior=1.0, model_noise_px=3.0, model_noise_rate=0.2)
    tracker = NCCTracker(options, face_model=model)
    true_xy = model.project(np.eye(3), model.t0, np.zeros(2))
    tracker.start(np.zeros((480, 640), np.float32), true_xy)
    information = np.broadcast_to(0.5 * np.eye(2), (len(SHAPE), 2, 2)).copy()
    ok = np.ones(len(SHAPE), bool)
    rng = np.random.default_rng(5)
    noise = np.full(len(SHAPE), 9.0)  # model_noise_px^2
    for _ in range(30):
        found = true_xy + rng.normal(0, 0.1, true_xy.shape)
        found[0] += rng.normal(0, 6.0, 2)  # a wandering match
        q = tracker.reliability()
        fused = tracker.with_model(found, information, ok)
        p = tracker.fit.xy
        np.testing.assert_allclose(fused, (0.5 * q[:, None] * found + p) / (0.5 * q[:, None] + 1.0), atol=1e-9)
        noise = 0.8 * noise + 0.2 * ((found - p) ** 2).sum(axis=1)
    np.testing.assert_allclose(tracker.noise, noise, rtol=1e-9)
    q = tracker.reliability()
    assert q[0] < 0.5 and np.all(q[1:] == 4.0)
    np.testing.assert_allclose(q, np.minimum(9.0 / noise, 4.0))
    # a point not matched this frame keeps its running mean and takes the model's position
    ok[1] = False
    before = tracker.noise[1]
    fused = tracker.with_model(true_xy + 5.0, information, ok)
    assert tracker.noise[1] == before
    np.testing.assert_allclose(fused[1], tracker.fit.xy[1], atol=1e-9)
