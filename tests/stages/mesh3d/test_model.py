"""The target's 3D model: lifting, depth from the posed generic model, the mesh, on the fixture pack."""

import numpy as np
import pytest

from stages.actor_pack import load_pack
from stages.mesh3d.model import build_target_model, fit_generic_depth, lift, skin_triangles

A = np.array([[384.0, 0.0, 119.5], [0.0, 384.0, 159.5], [0.0, 0.0, 1.0]])


def project(X: np.ndarray) -> np.ndarray:
    q = X @ A.T
    return q[..., :2] / q[..., 2:3]


def test_lift_reprojects_exactly_and_has_the_given_depth():
    rng = np.random.default_rng(0)
    X = rng.uniform(-80, 80, (3, 20, 3)) + np.array([0, 0, 400.0])
    lifted = lift(project(X), X[..., 2], A)
    np.testing.assert_allclose(lifted, X, rtol=1e-12)


def test_generic_depth_is_exact_when_the_model_is_the_face():
    rng = np.random.default_rng(1)
    model = rng.uniform(-60, 60, (30, 3))
    model[:, 2] *= 0.4
    angle = np.deg2rad(10.0)
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    t = np.array([5.0, -3.0, 350.0])
    depth, R_fit, t_fit = fit_generic_depth(model, project(model @ R.T + t), A)
    np.testing.assert_allclose(depth, (model @ R.T + t)[:, 2], atol=1e-6)
    np.testing.assert_allclose(R_fit, R, atol=1e-8)


def test_fixture_model_depth_error_is_bounded_and_the_mesh_is_counter_clockwise():
    pack = load_pack("fixtures/packs/target")
    truth = np.load("fixtures/packs/target/truth.npz")
    model = build_target_model(pack, pack.model3d, pack.intrinsics)
    true3d = truth["neutral_points3d"] @ truth["R"].T + truth["t"]
    skin = np.array([not n.startswith("teeth_") for n in model.names])
    err = np.linalg.norm(model.neutral - true3d, axis=1)[skin]
    assert err.mean() < 15.0  # the generic model's scale: ~10 mm, mostly one depth offset
    offset = (model.neutral - true3d)[skin].mean(0)
    assert np.linalg.norm(model.neutral - true3d - offset, axis=1)[skin].mean() < 5.0
    np.testing.assert_allclose(project(model.examples), np.stack([e.points for e in pack.examples]), atol=1e-9)
    p = pack.standard.points[model.triangles]
    area = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 1, 1] - p[:, 0, 1]) * (p[:, 2, 0] - p[:, 0, 0])
    assert np.all(area > 0)
    assert not np.isin(np.flatnonzero(~skin), model.triangles).any()
    assert model.members.shape == (len([s for s in pack.layout.subregions if not s.teeth]), len(model.names))


def test_skin_triangles_and_fit_check_inputs():
    with pytest.raises(ValueError, match="at least 6"):
        fit_generic_depth(np.zeros((5, 3)), np.zeros((5, 2)), A)
    pts = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0], [5.0, 5.0]])
    tri = skin_triangles(pts, np.array([True, True, True, True, False]))
    assert len(tri) == 2 and 4 not in tri
