"""The texture oracle recovers the coefficients an image was composited with (eq. 6 per subregion)."""

import numpy as np
import pytest
import torch

from stages.synthesis.build import build_synthesis_model
from stages.synthesis.composite import composite, prepare_compositor
from lab.synthesis.oracle import texture_oracle
from tests.stages.synthesis.synthetic import make_pack


@pytest.fixture(scope="module")
def model():
    return build_synthesis_model(make_pack(n_examples=4, n_teeth=2), band_px=0.0)  # no bands: each pixel one subregion


def random_coeffs(rng: np.random.Generator, model, *, shared: bool) -> torch.Tensor:
    """(2, S, K) coefficients on the simplex: face subregions over the examples (one vector for
    all of them when ``shared``), the teeth subregion over the teeth examples."""
    teeth = np.asarray(model["subregion_teeth"], bool)
    M, Mt = len(model["examples"]), len(model["teeth"])
    c = np.zeros((2, len(teeth), max(M, Mt)))
    for b in range(2):
        one = rng.dirichlet(np.ones(M))
        for s in range(len(teeth)):
            c[b, s, : Mt if teeth[s] else M] = (
                rng.dirichlet(np.ones(Mt)) if teeth[s] else (one if shared else rng.dirichlet(np.ones(M)))
            )
    return torch.from_numpy(c)


@pytest.mark.parametrize("mode", ["full", "global"])
def test_oracle_recovers_the_compositing_coefficients(model, mode):
    rng = np.random.default_rng(3)
    truth_c = random_coeffs(rng, model, shared=mode == "global")
    image = composite(prepare_compositor(dict(model)), truth_c, min_coeff=0.0)[:, :3]
    found = texture_oracle(model, image, mode=mode)
    np.testing.assert_allclose(found.numpy(), truth_c.numpy(), atol=2e-3)


def test_global_oracle_shares_one_combination_and_fits_no_better_than_per_subregion(model):
    rng = np.random.default_rng(4)
    image = composite(prepare_compositor(dict(model)), random_coeffs(rng, model, shared=False), min_coeff=0.0)[:, :3]
    full, glob = texture_oracle(model, image, mode="full"), texture_oracle(model, image, mode="global")
    teeth = np.asarray(model["subregion_teeth"], bool)
    face = glob[:, ~torch.from_numpy(teeth)]
    assert torch.allclose(face, face[:, :1].expand_as(face))
    comp = prepare_compositor(dict(model))
    err = [float(((composite(comp, c, min_coeff=0.0)[:, :3] - image) ** 2).sum()) for c in (full, glob)]
    assert err[0] < 1e-3 < err[1]


def test_oracle_rejects_bad_input(model):
    W, H = (int(v) for v in model["size"])
    with pytest.raises(ValueError, match="truth must be"):
        texture_oracle(model, torch.zeros(1, 3, H + 1, W))
    with pytest.raises(ValueError, match="mode"):
        texture_oracle(model, torch.zeros(1, 3, H, W), mode="warp-only")
