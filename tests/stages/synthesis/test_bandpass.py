"""Band-pass blending: the band split against scipy, the sharpened weights, and the compositor
with detail bands against an independent numpy computation."""

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter

from stages.synthesis.bandpass import detail_band, gaussian_lowpass, sharpened
from stages.synthesis.build import build_synthesis_model, subregion_weights
from stages.synthesis.composite import composite, prepare_compositor
from tests.stages.synthesis.synthetic import make_pack


def test_lowpass_matches_scipy_and_the_bands_sum_back_to_the_image():
    rng = np.random.default_rng(0)
    images = rng.uniform(0, 1, (2, 3, 30, 41))
    low = gaussian_lowpass(torch.from_numpy(images), sigma_px=2.0).numpy()
    ref = np.stack([[gaussian_filter(ch, 2.0, truncate=3.0, mode="mirror") for ch in im] for im in images])
    np.testing.assert_allclose(low, ref, atol=1e-12)
    detail = detail_band(torch.from_numpy(images), sigma_px=2.0).numpy()
    np.testing.assert_allclose(low + detail, images, atol=1e-12)
    flat = np.full((1, 3, 20, 20), 0.4)
    np.testing.assert_allclose(detail_band(torch.from_numpy(flat), sigma_px=1.5).numpy(), 0.0, atol=1e-12)
    with pytest.raises(ValueError, match="sigma_px"):
        gaussian_lowpass(torch.from_numpy(images), sigma_px=0.0)


def test_sharpened_weights():
    c = np.array([[0.5, 0.3, 0.2, 0.0], [0.4, 0.4, 0.2, 0.0]])
    np.testing.assert_allclose(sharpened(c, power=1.0), c)
    np.testing.assert_allclose(sharpened(c, power=2.0)[0], np.array([0.25, 0.09, 0.04, 0.0]) / 0.38)
    np.testing.assert_allclose(sharpened(c, power=np.inf), [[1, 0, 0, 0], [0.5, 0.5, 0, 0]])
    np.testing.assert_allclose(sharpened(c, power=1e6), [[1, 0, 0, 0], [0.5, 0.5, 0, 0]], atol=1e-12)
    with pytest.raises(ValueError, match="power"):
        sharpened(c, power=0.5)
    with pytest.raises(ValueError, match="positive"):
        sharpened(np.zeros((1, 3)), power=2.0)


def numpy_bandpass(model: dict, coeffs: np.ndarray, power: float, sigma: float) -> np.ndarray:
    """sum_s w_s(p) [sum_i c_si L_i(p) + sum_i c^_si D_i(p)], bands by scipy; outside = the outside image (the aligned neutral)."""
    S = len(model["subregion_teeth"])
    w = subregion_weights(model["blend_r"], model["blend_i1"], model["blend_i2"], n_labels=S + 1)
    out = w[S][..., None] * model["outside"].astype(np.float64) / 255
    for s in range(S):
        imgs = (model["teeth"] if model["subregion_teeth"][s] else model["examples"]).astype(np.float64) / 255
        low = np.stack(
            [np.stack([gaussian_filter(im[..., ch], sigma, truncate=3.0, mode="mirror") for ch in range(3)], -1) for im in imgs]
        )
        c = coeffs[s, : len(imgs)]
        c_hat = c**power / (c**power).sum()
        out += w[s][..., None] * (np.einsum("i,ihwc->hwc", c, low) + np.einsum("i,ihwc->hwc", c_hat, imgs - low))
    return out


def test_compositor_with_detail_bands_matches_numpy():
    model = build_synthesis_model(make_pack(), band_px=6.0)
    comp = prepare_compositor(model, detail_power=3.0, detail_sigma_px=1.5)
    c = np.random.default_rng(2).dirichlet(np.ones(4), size=(2, 7))
    c[:, -1, 2:] = 0  # the teeth row: two teeth examples
    c /= c.sum(-1, keepdims=True)
    sparse = composite(comp, torch.from_numpy(c), min_coeff=0.0)
    direct = composite(comp, torch.from_numpy(c), direct=True)
    plain = composite(prepare_compositor(model), torch.from_numpy(c), min_coeff=0.0)
    for b in range(2):
        ref = numpy_bandpass(model, c[b], 3.0, 1.5)
        np.testing.assert_allclose(sparse[b, :3].permute(1, 2, 0).numpy(), ref, atol=2e-5)
        np.testing.assert_allclose(direct[b, :3].permute(1, 2, 0).numpy(), ref, atol=2e-5)
        assert np.abs(plain[b, :3].permute(1, 2, 0).numpy() - ref).max() > 1e-2  # the detail weights matter
