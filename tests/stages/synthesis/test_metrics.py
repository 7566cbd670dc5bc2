"""PSNR / SSIM against independent numpy + scipy.ndimage computations."""

import numpy as np
import torch
from scipy.ndimage import gaussian_filter

from stages.synthesis.metrics import masked_psnr, masked_ssim, ssim_map


def scipy_ssim(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Wang et al. 2004 with scipy's Gaussian filter (sigma 1.5, truncated at radius 5, mirror edges)."""
    c1, c2 = 0.01**2, 0.03**2
    out = []
    for ch in range(a.shape[0]):
        f = lambda t: gaussian_filter(t, 1.5, truncate=3.5, mode="mirror")  # noqa: E731
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
    assert abs(masked_ssim(torch.from_numpy(a), torch.from_numpy(b), torch.from_numpy(mask)) - scipy_ssim(a, b)[mask].mean()) < 1e-10


def test_masked_psnr():
    a = np.zeros((3, 10, 10))
    b = a.copy()
    b[:, :5] = 0.1  # MSE 0.01 on the masked half -> 20 dB; unmasked pixels ignored
    b[:, 5:] = 0.5
    mask = np.zeros((10, 10), bool)
    mask[:5] = True
    assert abs(masked_psnr(torch.from_numpy(a), torch.from_numpy(b), torch.from_numpy(mask)) - 20.0) < 1e-9
