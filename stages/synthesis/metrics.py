"""Image quality over a mask: PSNR and SSIM (Wang et al. 2004), in torch, for the benchmarks.

SSIM uses the standard settings: an 11 x 11 Gaussian window of sigma 1.5, ``K1 = 0.01``,
``K2 = 0.03``, data range 1; local statistics are computed with reflect padding (whole-sample
symmetric, ``d c b | a b c d``), per channel, and the SSIM map is averaged over the channels
and then over the mask.
"""

from __future__ import annotations


__all__ = ["masked_psnr", "ssim_map", "masked_ssim"]


def masked_psnr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor, *, data_range: float = 1.0) -> float:
    """PSNR in dB over the pixels where ``mask`` is true.

    Parameters
    ----------
    a, b : (C, H, W) tensors
    mask : (H, W) bool tensor
    """
    import torch
    diff = (a.double() - b.double())[:, mask]
    mse = float((diff * diff).mean())
    return float("inf") if mse == 0 else 10.0 * float(torch.log10(torch.tensor(data_range**2 / mse)))


def ssim_map(a: torch.Tensor, b: torch.Tensor, *, data_range: float = 1.0, sigma: float = 1.5, radius: int = 5) -> torch.Tensor:
    """Per-pixel SSIM, averaged over channels.

    Parameters
    ----------
    a, b : (C, H, W) tensors in ``[0, data_range]``

    Returns
    -------
    (H, W) float64 tensor.
    """
    import torch
    import torch.nn.functional as F
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    g = torch.exp(-(x * x) / (2 * sigma * sigma))
    g = g / g.sum()
    C = a.shape[0]
    kx = g.view(1, 1, 1, -1).expand(C, 1, 1, -1).to(a.device)
    ky = g.view(1, 1, -1, 1).expand(C, 1, -1, 1).to(a.device)

    def blur(t: torch.Tensor) -> torch.Tensor:
        t = F.pad(t[None], (radius, radius, radius, radius), mode="reflect")
        return F.conv2d(F.conv2d(t, kx, groups=C), ky, groups=C)[0]

    a, b = a.double(), b.double()
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    mu_a, mu_b = blur(a), blur(b)
    var_a = blur(a * a) - mu_a * mu_a
    var_b = blur(b * b) - mu_b * mu_b
    cov = blur(a * b) - mu_a * mu_b
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a * mu_a + mu_b * mu_b + c1) * (var_a + var_b + c2))
    return s.mean(0)


def masked_ssim(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor, *, data_range: float = 1.0) -> float:
    """Mean SSIM over the pixels where ``mask`` (H, W) is true; ``a, b`` are (C, H, W)."""
    return float(ssim_map(a, b, data_range=data_range)[mask].mean())
