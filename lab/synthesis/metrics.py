"""Image quality over a mask: PSNR and SSIM (Wang et al. 2004), in torch, for the benchmarks.

SSIM uses the standard settings: an 11 x 11 Gaussian window of sigma 1.5, ``K1 = 0.01``,
``K2 = 0.03``, data range 1; local statistics are computed with reflect padding (whole-sample
symmetric, ``d c b | a b c d``), per channel, and the SSIM map is averaged over the channels
and then over the mask.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only; imported where used, so that importing this module stays light
    import torch

__all__ = ["masked_psnr", "ssim_map", "masked_ssim", "subregion_errors", "pooled_psnr"]


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


def subregion_errors(a: torch.Tensor, b: torch.Tensor, region: np.ndarray, names: Sequence[str]) -> dict[str, tuple[float, int]]:
    """Squared error over each subregion's pixels, for PSNR pooled over images (:func:`pooled_psnr`).

    Parameters
    ----------
    a, b : (C, H, W) tensors
    region : (H, W) int array
        Subregion index per pixel (``stages.layout.subregion_mask`` on the true geometry), negative
        or ``>= len(names)`` outside every subregion.
    names : sequence of str
        Subregion names in index order.

    Returns
    -------
    dict name -> (sum of squared differences, number of values summed) for the subregions that
    cover at least one pixel.
    """
    import torch

    region = np.asarray(region)
    if region.shape != tuple(a.shape[-2:]):
        raise ValueError(f"region must have the images' shape {tuple(a.shape[-2:])}, got {region.shape}")
    out = {}
    for k, name in enumerate(names):
        mask = torch.from_numpy(region == k).to(a.device)
        if mask.any():
            diff = (a.double() - b.double())[:, mask]
            out[str(name)] = (float((diff * diff).sum()), int(diff.numel()))
    return out


def pooled_psnr(errors: Sequence[Mapping[str, tuple[float, int]]], *, data_range: float = 1.0) -> dict[str, float]:
    """Per name, the PSNR (dB) of the mean squared error pooled over all images that have it.

    Pooling (rather than averaging per-image PSNR) keeps an image that reproduces a subregion
    exactly (infinite or 100+ dB PSNR, e.g. a brow that no expression moved) from dominating the
    mean. ``errors``: :func:`subregion_errors` of each image.
    """
    out = {}
    for name in dict.fromkeys(n for e in errors for n in e):
        sse = sum(e[name][0] for e in errors if name in e)
        count = sum(e[name][1] for e in errors if name in e)
        out[name] = float("inf") if sse == 0 else float(10.0 * np.log10(data_range**2 * count / sse))
    return out
