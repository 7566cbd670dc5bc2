"""Band-pass blending (Sec. 15 remedy): coarse shading by the convex coefficients, fine texture sharper.

Blending several examples pixel-wise (eq. 6) averages fine texture (brow hairs, eyelashes, teeth
edges) that is not pixel-aligned across them into a blur (the paper's Sec. 15, "pixel
misalignment"). Each aligned example is split into a low band ``L_i = G_sigma * I_i`` and a
detail band ``D_i = I_i - L_i`` (so ``L_i + D_i = I_i`` exactly); the low bands are blended with
the coefficients ``c_i`` of the QP (eq. 2-5) and the detail bands with sharpened weights

    c^_i = c_i^p / sum_j c_j^p                                         (p = ``detail_power``)

so that the blended image is

    I = sum_i c_i L_i + sum_i c^_i D_i = sum_i c_i I_i + sum_i (c^_i - c_i) D_i.

``p = 1`` is eq. 6 unchanged; ``p = inf`` takes the detail of the dominant example alone (ties
share it equally); finite ``p > 1`` moves continuously between the two, so that the detail does
not switch abruptly between frames when two examples trade places.
"""

from __future__ import annotations

import math

import numpy as np

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only; imported where used, so that importing this module stays light
    import torch

__all__ = ["gaussian_lowpass", "detail_band", "sharpened"]


def gaussian_lowpass(images: torch.Tensor, *, sigma_px: float) -> torch.Tensor:
    """Separable Gaussian blur, reflect padding (``d c b | a b c d``), radius ``ceil(3 sigma)``.

    Parameters
    ----------
    images : (E, C, H, W) float tensor
    sigma_px : float
        Standard deviation, px (> 0).

    Returns
    -------
    (E, C, H, W) tensor, same dtype and device.
    """
    import torch
    import torch.nn.functional as F

    if images.ndim != 4:
        raise ValueError(f"images must be (E, C, H, W), got shape {tuple(images.shape)}")
    if not sigma_px > 0:
        raise ValueError(f"sigma_px must be > 0, got {sigma_px}")
    radius = int(math.ceil(3.0 * sigma_px))
    radius = min(radius, images.shape[-1] - 1, images.shape[-2] - 1)
    x = torch.arange(-radius, radius + 1, dtype=images.dtype, device=images.device)
    g = torch.exp(-(x * x) / (2.0 * sigma_px * sigma_px))
    g = g / g.sum()
    C = images.shape[1]
    t = F.pad(images, (radius, radius, radius, radius), mode="reflect")
    t = F.conv2d(t, g.view(1, 1, 1, -1).expand(C, 1, 1, -1), groups=C)
    return F.conv2d(t, g.view(1, 1, -1, 1).expand(C, 1, -1, 1), groups=C)


def detail_band(images: torch.Tensor, *, sigma_px: float) -> torch.Tensor:
    """The detail band ``D = I - G_sigma * I`` of (E, C, H, W) images (see :func:`gaussian_lowpass`)."""
    return images - gaussian_lowpass(images, sigma_px=sigma_px)


def sharpened(coeffs: np.ndarray, *, power: float) -> np.ndarray:
    """The detail weights ``c^_i = c_i^p / sum_j c_j^p`` along the last axis.

    Parameters
    ----------
    coeffs : (..., K) float array, non-negative, not all zero along the last axis
    power : float
        ``p >= 1``; ``inf`` gives the indicator of the largest coefficient (ties share equally).

    Returns
    -------
    (..., K) float64, each row summing to 1.
    """
    c = np.asarray(coeffs, np.float64)
    if not power >= 1:
        raise ValueError(f"power must be >= 1, got {power}")
    if (c < 0).any():
        raise ValueError("coefficients must be non-negative")
    top = c.max(-1, keepdims=True)
    if (top <= 0).any():
        raise ValueError("every row of coefficients needs a positive entry")
    w = (c == top).astype(np.float64) if math.isinf(power) else (c / top) ** power
    return w / w.sum(-1, keepdims=True)
