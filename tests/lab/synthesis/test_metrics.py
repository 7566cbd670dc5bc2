"""PSNR / SSIM against independent numpy + scipy.ndimage computations."""

import numpy as np
import torch
from scipy.ndimage import gaussian_filter

from lab.synthesis.metrics import masked_psnr, masked_ssim, ssim_map


def scipy_ssim(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Wang et al. 2004 with scipy's Gaussian filter (sigma 1.5, truncated at radius 5, mirror edges)."""
    c1, c2 = 0.01**2, 0.03**2
    out = []
    for ch in range(a.shape[0]):
        f = lambda t: gaussian_filter(t, 1.5, truncate=3.5, mode="mirror")
        x, y = a[ch], b[ch]
        mx, my = f(x), f(y)
        vx, vy, cxy = f(x * x) - mx**2, f(y * y) - my**2, f(x * y) - mx * my
        out.append(((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2)))
    return np.mean(out, 0)


def test_ssim_matches_scipy_and_known_values():
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 1, (3, 40, 50))
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1)
    ours = ssim_map(torch.from_numpy(a), torch.from_numpy(b)).numpy()
    np.testing.assert_allclose(ours, scipy_ssim(a, b), atol=1e-10)
    assert masked_ssim(torch.from_numpy(a), torch.from_numpy(a), torch.ones(40, 50, dtype=torch.bool)) == 1.0
    mask = np.zeros((40, 50), bool)
    mask[5:20, 10:30] = True
    assert (
        abs(masked_ssim(torch.from_numpy(a), torch.from_numpy(b), torch.from_numpy(mask)) - scipy_ssim(a, b)[mask].mean()) < 1e-10
    )


def test_masked_psnr():
    a = np.zeros((3, 10, 10))
    b = a.copy()
    b[:, :5] = 0.1  # MSE 0.01 on the masked half -> 20 dB; unmasked pixels ignored
    b[:, 5:] = 0.5
    mask = np.zeros((10, 10), bool)
    mask[:5] = True
    assert abs(masked_psnr(torch.from_numpy(a), torch.from_numpy(b), torch.from_numpy(mask)) - 20.0) < 1e-9


def test_subregion_errors_pool_over_images():
    from lab.synthesis.metrics import pooled_psnr, subregion_errors

    region = np.full((4, 6), -1)
    region[:, :2] = 0
    region[:, 4:] = 1  # subregion 2 ("c") covers no pixel
    a = torch.zeros(3, 4, 6, dtype=torch.float64)
    b1, b2 = a.clone(), a.clone()
    b1[:, :, :2] = 0.1  # subregion a: MSE 0.01 in image 1, 0 in image 2 -> pooled 0.005
    b1[:, :, 2:4] = 0.7  # outside every subregion: ignored
    b2[:, :, 4:] = 0.01  # subregion b: exact in image 1, MSE 1e-4 in image 2
    e1 = subregion_errors(a, b1, region, ["a", "b", "c"])
    e2 = subregion_errors(a, b2, region, ["a", "b", "c"])
    assert set(e1) == {"a", "b"} and e1["a"][1] == 3 * 8
    pooled = pooled_psnr([e1, e2])
    assert abs(pooled["a"] - 10 * np.log10(1 / 0.005)) < 1e-9
    assert abs(pooled["b"] - 10 * np.log10(1 / 5e-5)) < 1e-9  # the exact image does not make it infinite
    assert pooled_psnr([e1])["b"] == float("inf")
