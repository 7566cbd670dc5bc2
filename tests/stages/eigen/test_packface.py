import os
from pathlib import Path

import numpy as np
import pytest

from stages.actor_pack import load_pack
from stages.eigen.model import analyze_frames, similarities_from_points
from stages.eigen.packface import PackFace, pca_parameters, point_depth
from stages.eigen.training import train_on_renders
from stages.layout import subregion_mask

PACK = Path(os.environ.get("EXPRESSION_FIXTURES", Path(__file__).resolve().parents[3] / "fixtures")) / "packs" / "performer"


@pytest.fixture(scope="module")
def face():
    return PackFace(load_pack(PACK))


def test_pca_parameters_recover_known_directions():
    rng = np.random.default_rng(0)
    e = np.linalg.qr(rng.normal(size=(8, 2)))[0].T.reshape(2, 4, 2)  # two orthonormal directions
    centred = rng.normal(size=(200, 2))
    centred -= centred.mean(axis=0)
    scores = np.linalg.qr(centred)[0] * [3.0, 1.0] * np.sqrt(199)  # uncorrelated, zero mean, sd 3 and 1
    captured = 10.0 + np.einsum("kc,cnd->knd", scores, e)
    basis = pca_parameters(captured, variance=0.999)
    assert basis.shape == (2, 4, 2)
    sd = (3.0, 1.0)
    for k in range(2):  # sigma_k e_k up to sign
        assert min(np.abs(basis[k] - sd[k] * e[k]).max(), np.abs(basis[k] + sd[k] * e[k]).max()) < 1e-9
    assert pca_parameters(captured, variance=0.5).shape == (1, 4, 2)
    assert pca_parameters(captured, variance=0.999, max_params=1).shape == (1, 4, 2)
    with pytest.raises(ValueError, match="K >= 2"):
        pca_parameters(captured[:1])


def test_point_depth_scales_the_model_to_the_neutral():
    model = np.array([[0.0, 0, 5], [10, 0, 0], [0, 10, 0], [10, 10, -5]])
    neutral = 3.0 * model[:, :2] + 7.0
    np.testing.assert_allclose(point_depth(model, neutral), [15.0, 0.0, 0.0, -15.0])


def test_zero_parameters_render_the_packs_neutral(face):
    pack = face.pack
    image, points = face.render(np.zeros(len(face.param_names)), np.zeros(3))
    W, H = pack.image_size
    assert image.shape == (H, W, 3) and image.dtype == np.uint8 and points.shape == (len(face.point_names), 2)
    np.testing.assert_allclose(points, pack.neutral.points, atol=1e-9)
    inside = subregion_mask(pack.layout, pack.neutral.points, pack.image_size) >= 0
    err = image[inside].astype(float) - pack.neutral.image[inside].astype(float)
    psnr = 10 * np.log10(255.0**2 / (err**2).mean())
    assert psnr > 30.0, psnr


def test_parameters_move_the_points_and_a_turn_moves_near_points_more(face):
    C = len(face.param_names)
    assert 1 <= C <= 8 and face.basis.shape == (C, len(face.point_names), 2)
    mu = np.zeros(C)
    mu[0] = 1.0
    np.testing.assert_allclose(face.points(mu) - face.neutral, face.basis[0], atol=1e-9)
    images, points = face.render_batch(np.zeros((2, C)), np.array([[0.0, 0, 0], [8.0, 0, 0]]))
    assert images.shape[0] == 2 and points.shape == (2, len(face.point_names), 2)
    shift = points[1, :, 0] - points[0, :, 0]
    near, far = np.argmin(face.depth), np.argmax(face.depth)
    assert abs(shift[near] - shift[far]) > 1.0  # out-of-plane rotation: parallax from the model's depth
    assert not np.array_equal(images[0], images[1])


def test_training_on_the_pack_face_reads_a_new_combination(face):
    C = len(face.param_names)
    params, angles = face.sampling("paper", samples=0, seed=0)
    assert params.shape == ((4 * C + 1) * 9, C) and angles.shape == (len(params), 3)
    front = (angles == 0).all(axis=1)  # fewer renders: the frontal orientation only
    model = train_on_renders(face, params[front], angles[front], q=3, blur_px=1.0)  # 17 renders: few rows
    low, high = face.param_range
    np.testing.assert_array_equal(model.param_low, low)
    np.testing.assert_array_equal(model.param_high, high)
    assert model.rigid == face.rigid and model.param_names == face.param_names
    truth = np.zeros((1, C))
    truth[0, :2] = (1.5, -1.0)  # a combination the paper's sampling never rendered
    image, points = face.render(truth[0], np.zeros(3))
    similarity, ok = similarities_from_points(model, points[None], np.ones((1, len(points)), bool))
    mu, feature_valid = analyze_frames(model, [image], similarity, ok, None)
    assert feature_valid.all() and mu.shape == (1, C)
    assert np.abs(mu - truth).mean() < 0.6 * np.abs(truth).mean(), (mu, truth)  # well better than the neutral
