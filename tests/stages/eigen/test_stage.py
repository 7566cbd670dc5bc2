import numpy as np
import pytest

from runner.stage import Context, StageError
from stages.eigen.stage import AnalyzeEigenfeatures, TrainEigenfeatures
from tests.memory_stream import MemoryStream
from tests.stages.eigen import scene
from tests.stages.eigen.toy import toy_model

CTX = Context(device="cpu", files_dir=lambda port: None)
PARAMS = {"model_file": "", "rotation": True, "ridge": 0.0}


@pytest.fixture(scope="module")
def bundle():
    return toy_model().to_bundle()


def clip(T=5):
    rng = np.random.default_rng(2)
    truth = rng.random((T, 4))
    sims = np.tile([1.0, 0.0, 0.0, 0.0], (T, 1))
    sims[-1, 2] = 70.0  # the last frame's feature b leaves the image
    frames = np.stack([scene.scene(p, s) for p, s in zip(truth, sims)])
    similarity = {"params": sims, "valid": np.ones(T, bool), "residual_px": np.zeros(T), "fps": np.array(25.0)}
    pose = {"R": np.tile(np.eye(3), (T, 1, 1)), "valid": np.ones(T, bool)}
    return MemoryStream(frames, chunk=2), similarity, pose, truth


def test_points_bundle_follows_the_contract(bundle):
    frames, similarity, pose, truth = clip()
    out = AnalyzeEigenfeatures().run({"frames": frames, "similarity": similarity, "pose": pose, "model": bundle}, PARAMS, CTX)
    points, params = out["points"], out["parameters"]
    assert points["xy"].shape == (5, 6, 2) and points["xy"].dtype == np.float64 and np.isfinite(points["xy"]).all()
    assert points["valid"].shape == (5, 6) and points["valid"].dtype == bool
    assert points["names"].tolist() == list(scene.NAMES) and float(points["fps"]) == 25.0
    assert params["params"].shape == (5, 4) and params["feature_valid"].shape == (5, 2)
    assert np.abs(params["params"][:4] - truth[:4]).max() < 0.05
    assert points["valid"][:4].all()
    assert points["valid"][4].tolist() == [True, True, True, False, False, False]  # feature b's points masked
    disp = out["displacements"]
    assert disp["d"].shape == (5, 6, 2) and disp["d"].dtype == np.float64 and disp["neutral"].shape == (6, 2)
    np.testing.assert_allclose((disp["neutral"][None] + disp["d"])[:4], points["xy"][:4], atol=1e-9)  # identity similarity
    np.testing.assert_array_equal(disp["valid"], points["valid"])


def test_model_file_and_errors(bundle, tmp_path):
    frames, similarity, pose, _ = clip(2)
    path = tmp_path / "model.npz"
    np.savez(path, **bundle)
    out = AnalyzeEigenfeatures().run(
        {"frames": frames, "similarity": similarity, "pose": pose}, {**PARAMS, "model_file": str(path)}, CTX
    )
    assert out["points"]["xy"].shape == (2, 6, 2)
    with pytest.raises(StageError, match="exactly one"):
        AnalyzeEigenfeatures().run(
            {"frames": frames, "similarity": similarity, "pose": pose, "model": bundle}, {**PARAMS, "model_file": str(path)}, CTX
        )
    with pytest.raises(StageError, match="pose"):
        AnalyzeEigenfeatures().run({"frames": frames, "similarity": similarity, "model": bundle}, PARAMS, CTX)
    with pytest.raises(StageError, match="3 frames"):
        short = {**similarity, "params": np.tile([1.0, 0, 0, 0], (3, 1)), "valid": np.ones(3, bool)}
        AnalyzeEigenfeatures().run({"frames": frames, "similarity": short, "model": bundle}, {**PARAMS, "rotation": False}, CTX)


def test_training_on_a_broken_pack_names_the_field(tmp_path):
    (tmp_path / "pack.yaml").write_text("format: actor-pack/1\nname: real\nimage_size: [320, 240]\n")
    params = {p.name: p.default for p in TrainEigenfeatures.params}
    with pytest.raises(StageError, match="field 'layout'"):
        TrainEigenfeatures().run({"pack": tmp_path}, params, CTX)


def test_similarity_from_points_matches_the_given_similarity(bundle):
    frames, similarity, pose, _ = clip()
    model_neutral = np.asarray(bundle["neutral"])
    xy = np.stack([model_neutral * s[0] + s[2:] for s in similarity["params"]])  # a = s, b = 0
    points = {"xy": xy, "valid": np.ones(xy.shape[:2], bool), "names": bundle["point_names"]}
    given = AnalyzeEigenfeatures().run({"frames": frames, "similarity": similarity, "pose": pose, "model": bundle}, PARAMS, CTX)
    fitted = AnalyzeEigenfeatures().run({"frames": frames, "points": points, "pose": pose, "model": bundle}, PARAMS, CTX)
    np.testing.assert_allclose(fitted["parameters"]["params"], given["parameters"]["params"], atol=1e-6)
    with pytest.raises(StageError, match="exactly one"):
        AnalyzeEigenfeatures().run({"frames": frames, "similarity": similarity, "points": points, "model": bundle}, PARAMS, CTX)
