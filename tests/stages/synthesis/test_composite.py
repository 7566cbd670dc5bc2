"""Compositing (eq. 6) with boundary blending (eq. 7) against an independent numpy computation."""

import numpy as np
import pytest
import torch

from stages.synthesis.build import build_synthesis_model, subregion_weights
from stages.synthesis.composite import composite, prepare_compositor, workspace
from tests.stages.synthesis.synthetic import make_pack


@pytest.fixture(scope="module")
def model():
    return build_synthesis_model(make_pack(), band_px=6.0)


def numpy_eq7(model: dict, coeffs: np.ndarray) -> np.ndarray:
    """sum_s w_s(p) sum_i c_si I_i(p) with the dense (S+1, H, W) weight tensor; outside = the outside image (the aligned neutral)."""
    S = len(model["subregion_teeth"])
    w = subregion_weights(model["blend_r"], model["blend_i1"], model["blend_i2"], n_labels=S + 1)
    ex = model["examples"].astype(np.float64) / 255
    teeth = model["teeth"].astype(np.float64) / 255
    out = w[S][..., None] * model["outside"].astype(np.float64) / 255
    for s in range(S):
        imgs = teeth if model["subregion_teeth"][s] else ex
        sub = np.einsum("i,ihwc->hwc", coeffs[s, : len(imgs)], imgs)  # eq. 6
        out += w[s][..., None] * sub  # eq. 7
    return out


def random_coeffs(rng: np.random.Generator, B: int, S: int, K: int) -> np.ndarray:
    c = rng.dirichlet(np.ones(K) * 0.7, size=(B, S))
    c[:, -1, 2:] = 0  # the teeth row: two teeth examples
    return c / c.sum(-1, keepdims=True)


def test_sparse_and_direct_match_numpy_eq7(model):
    comp = prepare_compositor(model)
    y0, y1, x0, x1 = comp.box
    W, H = comp.size
    assert 0 < y1 - y0 < H and 0 < x1 - x0 < W  # the sparse path composites inside the face box only
    c = random_coeffs(np.random.default_rng(0), 2, 7, 4)
    sparse = composite(comp, torch.from_numpy(c), min_coeff=0.0)
    direct = composite(comp, torch.from_numpy(c), direct=True)
    for b in range(2):
        ref = numpy_eq7(model, c[b])
        np.testing.assert_allclose(sparse[b, :3].permute(1, 2, 0).numpy(), ref, atol=2e-6)
        np.testing.assert_allclose(direct[b, :3].permute(1, 2, 0).numpy(), ref, atol=2e-6)
    S = 7
    w = subregion_weights(model["blend_r"], model["blend_i1"], model["blend_i2"], n_labels=S + 1)
    np.testing.assert_allclose(sparse[0, 3].numpy(), 1 - w[S], atol=1e-6)  # face alpha


def test_negligible_coefficients_are_skipped_and_the_rest_renormalised(model):
    comp = prepare_compositor(model)
    c = random_coeffs(np.random.default_rng(1), 1, 7, 4)
    c[0, :6] = [0.6, 0.3995, 0.0005, 0.0]
    out = composite(comp, torch.from_numpy(c), min_coeff=1e-3)
    expected = c.copy()
    expected[0, :6] = [0.6 / 0.9995, 0.3995 / 0.9995, 0, 0]
    np.testing.assert_allclose(out[0, :3].permute(1, 2, 0).numpy(), numpy_eq7(model, expected[0]), atol=2e-6)


def test_one_hot_coefficients_reproduce_the_aligned_example_inside_the_face(model):
    comp = prepare_compositor(model)
    c = np.zeros((1, 7, 4))
    c[0, :6, 1] = 1.0
    c[0, 6, 0] = 1.0
    out = composite(comp, torch.from_numpy(c))[0, :3].permute(1, 2, 0).numpy()
    face = (model["region"] < 6) & (model["blend_i2"] < 6)  # face subregions, no band towards teeth/outside
    np.testing.assert_allclose(out[face], model["examples"][1][face] / 255.0, atol=1e-6)


@pytest.mark.parametrize("detail_power", [1.0, 2.0])
def test_workspace_frames_equal_fresh_buffers_frame_after_frame(model, detail_power):
    """One workspace reused for frame after frame (face slices rewritten, background kept) gives
    bit for bit what fresh buffers give, also with band-pass detail terms."""
    comp = prepare_compositor(model, detail_power=detail_power)
    ws = workspace(comp)
    c = random_coeffs(np.random.default_rng(2), 4, 7, 4)
    c[1, :6] = [1.0, 0.0, 0.0, 0.0]  # a one-hot frame between spread ones: stale terms would show
    batch = composite(comp, torch.from_numpy(c))
    for b in range(4):
        one = composite(comp, torch.from_numpy(c[b : b + 1]), workspace=ws)
        assert one.data_ptr() == ws.standard.data_ptr()
        torch.testing.assert_close(one, batch[b : b + 1], rtol=0, atol=0)
    with pytest.raises(ValueError, match="one frame"):
        composite(comp, torch.from_numpy(c[:2]), workspace=ws)
    with pytest.raises(ValueError, match="one frame"):
        composite(comp, torch.from_numpy(c[:1]), workspace=ws, direct=True)


def test_teeth_examples_are_blended_with_sharpened_weights(model):
    """Two teeth examples at 0.6 / 0.4 (each with its teeth at its own place relative to the lips):
    an even-ish blend shows both rows of teeth, doubled. Sharpened to the 4th power the weaker one
    keeps 0.4^4 / (0.6^4 + 0.4^4) = 16.5 % of the teeth region."""
    S = len(model["subregion_teeth"])
    c = random_coeffs(np.random.default_rng(2), 1, S, 4)
    c[0, -1] = [0.6, 0.4, 0.0, 0.0]
    teeth = model["region"] == S - 1
    plain = composite(prepare_compositor(model), torch.from_numpy(c), min_coeff=0.0)[0, :3].permute(1, 2, 0).numpy()
    sharp = (
        composite(prepare_compositor(model, teeth_power=4.0), torch.from_numpy(c), min_coeff=0.0)[0, :3].permute(1, 2, 0).numpy()
    )
    T0, T1 = (model["teeth"][k].astype(np.float64) / 255 for k in (0, 1))
    w1 = 0.4**4 / (0.6**4 + 0.4**4)
    inside = teeth & (model["blend_r"] == 1)
    np.testing.assert_allclose(plain[inside], (0.6 * T0 + 0.4 * T1)[inside], atol=2e-6)
    np.testing.assert_allclose(sharp[inside], ((1 - w1) * T0 + w1 * T1)[inside], atol=2e-6)
    outside_teeth = ~teeth & (model["blend_i2"] == model["blend_i1"])
    np.testing.assert_allclose(sharp[outside_teeth], plain[outside_teeth], atol=1e-7)  # the face subregions as solved
