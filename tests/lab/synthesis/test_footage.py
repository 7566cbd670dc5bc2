"""Footage-learned coefficients: k-NN means, blocked cross-validation, per-subregion neighbourhoods."""

import numpy as np
import pytest
import torch

from stages.synthesis.build import build_synthesis_model
from stages.synthesis.composite import composite, prepare_compositor
from lab.synthesis.footage import FootageCoefficients, cv_errors, nearest_mean, subregion_distance
from lab.synthesis.oracle import texture_oracle
from tests.stages.synthesis.synthetic import make_pack


def test_nearest_mean_and_distance_match_loops():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(3, 5, 2)), rng.normal(size=(7, 5, 2))
    member = np.array([True, False, True, True, False])
    d = subregion_distance(a, b, member)
    for i in range(3):
        for j in range(7):
            assert d[i, j] == pytest.approx(np.sqrt(np.mean([np.sum((a[i, p] - b[j, p]) ** 2) for p in (0, 2, 3)])))
    values = torch.from_numpy(rng.dirichlet(np.ones(4), size=7))
    got = nearest_mean(d, values, 3)
    for i in range(3):
        chosen = sorted(range(7), key=lambda j: d[i, j])[:3]
        np.testing.assert_allclose(got[i].numpy(), values[chosen].numpy().mean(0))
    with pytest.raises(ValueError, match="k must be"):
        nearest_mean(d, values, 8)


def test_cv_errors_match_a_direct_texture_error():
    rng = np.random.default_rng(1)
    T, M, P, folds = 20, 4, 30, 4
    E = rng.uniform(size=(M, P))  # candidate textures
    truth = rng.uniform(size=(T, P))
    coeffs = torch.from_numpy(rng.dirichlet(np.ones(M), size=T))
    D = rng.uniform(size=(T, T))
    # Q_f = (E - T_f)(E - T_f)^T, so c^T Q_f c = ||sum c_i E_i - T_f||^2 on the simplex
    gram = torch.from_numpy(np.einsum("fip,fjp->fij", E[None] - truth[:, None], E[None] - truth[:, None]))
    ks = (1, 3, 20)
    got = cv_errors(D, coeffs, gram, ks=ks, folds=folds)
    runs = np.split(np.arange(T), folds)  # contiguous runs of T / folds frames
    expected = []
    for k in ks:
        total = 0.0
        for run in runs:
            train = [j for j in range(T) if j not in run]
            for f in run:
                near = sorted(train, key=lambda j: D[f, j])[: min(k, len(train))]
                c = coeffs.numpy()[near].mean(0)
                total += float(np.sum((c @ E - truth[f]) ** 2))
        expected.append(total)
    np.testing.assert_allclose(got, expected, rtol=1e-10)
    with pytest.raises(ValueError, match="folds"):
        cv_errors(D, coeffs, gram, ks=ks, folds=1)


@pytest.fixture(scope="module")
def model():
    return build_synthesis_model(make_pack(n_examples=4, n_teeth=2), band_px=0.0)  # no bands: each pixel one subregion


def test_each_subregion_takes_the_texture_of_the_footage_frame_nearest_in_its_own_points(model):
    """Footage: frame 1 moves only point g00 (cell00's corner), frame 2 only g30 (cell20's); a
    target moving both takes cell00's texture from frame 1 and cell20's from frame 2 per subregion,
    one frame's global oracle combination everywhere in global mode."""
    rng = np.random.default_rng(2)
    teeth = np.asarray(model["subregion_teeth"], bool)
    S, M, Mt = len(teeth), len(model["examples"]), len(model["teeth"])
    truth_c = np.zeros((4, S, max(M, Mt)))
    for f in range(4):
        for s in range(S):
            truth_c[f, s, : Mt if teeth[s] else M] = rng.dirichlet(np.ones(Mt if teeth[s] else M))
    images = composite(prepare_compositor(dict(model)), torch.from_numpy(truth_c), min_coeff=0.0)[:, :3]
    base = np.asarray(model["standard_points"], np.float64)
    footage = np.stack([base] * 4)
    footage[1, 0] += (6.0, 0.0)  # g00
    footage[2, 3] += (-6.0, 0.0)  # g30
    target = base.copy()
    target[0] += (6.0, 0.0)
    target[3] += (-6.0, 0.0)
    fc = FootageCoefficients(model, footage, images, ks=(1,), folds=2)
    assert fc.k == {"full": 1, "global": 1}
    names = list(np.asarray(model["subregion_names"], str))
    full = fc.coefficients(target[None], mode="full")[0].numpy()
    np.testing.assert_allclose(full[names.index("cell00"), :M], truth_c[1, names.index("cell00"), :M], atol=2e-3)
    np.testing.assert_allclose(full[names.index("cell20"), :M], truth_c[2, names.index("cell20"), :M], atol=2e-3)
    glob = fc.coefficients(target[None], mode="global")[0].numpy()
    oracle = texture_oracle(model, images[1:2], mode="global")[0].numpy()  # frames 1 and 2 tie: the first
    np.testing.assert_allclose(glob[~teeth], oracle[~teeth], atol=1e-9)
    qp, _ = fc.qp.coefficients(target[None], mode="full")
    np.testing.assert_allclose(full[teeth], qp[0].numpy()[teeth])  # teeth by eq. 2 in both modes
    np.testing.assert_allclose(glob[teeth], qp[0].numpy()[teeth])


def test_footage_coefficients_reject_bad_input(model):
    W, H = (int(v) for v in model["size"])
    N = len(model["standard_points"])
    with pytest.raises(ValueError, match="same T"):
        FootageCoefficients(model, np.zeros((3, N, 2)), torch.zeros(2, 3, H, W))
    with pytest.raises(ValueError, match="ks"):
        FootageCoefficients(model, np.zeros((2, N, 2)), torch.zeros(2, 3, H, W), ks=(0,))
    fc = FootageCoefficients(model, np.zeros((2, N, 2)), torch.zeros(2, 3, H, W), ks=(1,), folds=2)
    with pytest.raises(ValueError, match="mode"):
        fc.coefficients(np.zeros((1, N, 2)), mode="warp-only")
