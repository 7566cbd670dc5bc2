import numpy as np
import pytest

from stages.eigen.model import EigenModel, analyze_frames, parameters_to_points
from stages.eigen.sampling import paper_sampling, rich_sampling
from stages.geometry.rotation import ypr_zyx
from tests.stages.eigen import scene
from tests.stages.eigen.toy import MOTION, random_similarity, toy_model


@pytest.fixture(scope="module")
def model():
    return toy_model()


# normalizing each patch by its own contrast makes the scores a little non-linear in the parameters
@pytest.mark.parametrize("conditioning, tolerance", [({}, 0.05), ({"blur_px": 1.0, "normalize": True}, 0.1)])
def test_parameters_are_recovered_from_new_frames(model, conditioning, tolerance):
    if conditioning:
        model = toy_model(**conditioning)
    rng = np.random.default_rng(11)
    truth = rng.random((6, 4))
    sims = np.stack([random_similarity(rng) for _ in truth])
    frames = [scene.scene(p, T) for p, T in zip(truth, sims)]
    mu, fv = analyze_frames(model, frames, sims, np.ones(6, bool), np.zeros((6, 3)))
    assert mu.shape == (6, 4) and mu.dtype == np.float64 and fv.shape == (6, 2) and fv.dtype == bool
    assert fv.all()
    assert np.abs(mu - truth).max() < tolerance


def test_masked_feature_keeps_the_other_features_parameters(model):
    truth = np.array([[0.7, 0.2, 0.5, 0.9]])
    T = np.array([[1.0, 0.0, 70.0, 0.0]])  # feature b leaves the image
    mu, fv = analyze_frames(model, [scene.scene(truth[0], T[0])], T, np.ones(1, bool), np.zeros((1, 3)))
    assert fv.tolist() == [[True, False]]
    assert np.abs(mu[0, :2] - truth[0, :2]).max() < 0.1  # parameters seen by feature a


def test_invalid_frame_gives_nan(model):
    mu, fv = analyze_frames(
        model, [scene.scene(np.zeros(4), np.array([1.0, 0, 0, 0]))], np.array([[1.0, 0, 0, 0]]), np.zeros(1, bool), None
    )
    assert np.isnan(mu).all() and not fv.any()


def test_geometry_map_and_similarity(model):
    mu = np.array([[1.0, 0.0, 0.0, 1.0]])
    np.testing.assert_allclose(parameters_to_points(model, mu)[0], scene.NEUTRAL + MOTION[0] + MOTION[3], atol=1e-9)
    T = np.array([[0.0, 1.0, 10.0, 0.0]])  # 90 deg
    xy = parameters_to_points(model, np.zeros((1, 4)), T)[0]
    np.testing.assert_allclose(xy[:, 0], 10.0 - scene.NEUTRAL[:, 1], atol=1e-9)


def test_bundle_round_trip_keeps_the_estimates(model):
    bundle = model.to_bundle()
    assert all(v.dtype != object for v in bundle.values())
    again = EigenModel.from_bundle(bundle)
    assert again.windows == model.windows and again.q == model.q
    np.testing.assert_array_equal(again.estimator(np.ones(2, bool)), model.estimator(np.ones(2, bool)))
    with pytest.raises(ValueError, match="gram"):
        EigenModel.from_bundle({k: v for k, v in bundle.items() if k != "gram"})


def test_samplings():
    c, a = paper_sampling(12)
    assert c.shape == (441, 12) and a.shape == (441, 3)
    assert set(np.unique(c)) == {0.0, 0.25, 0.5, 0.75, 1.0}
    assert ((c > 0).sum(axis=1) <= 1).all()  # each parameter alone
    assert set(map(tuple, a[:9])) == {(y, p, 0.0) for y in (-3.0, 0.0, 3.0) for p in (-3.0, 0.0, 3.0)}
    c, a = rich_sampling(12, 50, seed=1)
    assert c.shape == (50, 12) and 0 <= c.min() and c.max() <= 1 and np.all(np.abs(a).max(axis=0) <= [25, 15, 10])


def test_ypr_zyx_inverts_the_generators_rotation():
    from stages.eigen.facegen.render import rotation

    for angles in ((10.0, -5.0, 3.0), (-25.0, 15.0, -10.0)):
        np.testing.assert_allclose(ypr_zyx(rotation(*angles)), angles, atol=1e-9)
