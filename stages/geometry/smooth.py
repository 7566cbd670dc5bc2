"""Temporal smoothing of feature point trajectories with a Gaussian kernel (paper Sec. 14.1: "the
tracking result is very noisy, so we first smooth each feature point trajectory by using a
Gaussian kernel").

The smoothing is a normalized convolution: each sample is weighted by the kernel times its
validity, and the weighted sum is divided by the sum of the weights that were used, so an
invalid sample contributes nothing and a gap is filled from its valid neighbours where they
carry enough of the kernel's mass.

At the clip's ends the trajectory is continued by odd reflection about the end sample,
``x(-k) = 2 x(0) - x(k)`` (and likewise after the last frame). A constant and a linear motion
pass through unchanged, and the end sample itself is kept: the first frame, which the tracker
was given and the pipeline takes as the neutral, stays exactly where it was. (Renormalizing the
truncated kernel instead would pull each end towards the motion next to it: 3.5 px mean at
frame 0 of the live fixture clip, sigma 1.5.) Where the end sample is invalid, its reflection is
too, and the kernel is renormalized over what is left.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np
from scipy.ndimage import convolve1d

from runner.stage import Context, Param, SequenceStage, StageError


def gaussian_kernel(sigma: float, *, truncate: float = 3.0) -> np.ndarray:
    """Normalized 1D Gaussian ``(2r + 1,)`` with ``r = ceil(truncate * sigma)``; ``[1.]`` for sigma 0."""
    if sigma < 0:
        raise ValueError(f"sigma must be >= 0, got {sigma}")
    if sigma == 0:
        return np.ones(1)
    radius = int(np.ceil(truncate * sigma))
    t = np.arange(-radius, radius + 1, dtype=np.float64)
    kernel = np.exp(-0.5 * (t / sigma) ** 2)
    return kernel / kernel.sum()


def gaussian_smooth(
    values: np.ndarray, valid: np.ndarray | None = None, *, sigma: float, truncate: float = 3.0,
    min_support: float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """Smooth trajectories over time (axis 0) by normalized Gaussian convolution.

    ``out[t] = sum_k g_k m_{t+k} x_{t+k} / sum_k g_k m_{t+k}``, with ``g`` the Gaussian of
    :func:`gaussian_kernel`, ``m`` the validity mask, and ``x``, ``m`` continued past the clip's
    ends by :func:`odd_reflection` / :func:`reflection_mask`.

    Parameters
    ----------
    values : (T, ...) float
        Trajectories, e.g. points ``(T, N, 2)`` px or quaternions ``(T, 4)``.
    valid : (T, ...) bool, optional
        Mask with the leading axes of ``values`` (``(T, N)`` for points); if omitted, ``(T,)``
        all valid.
    sigma : float
        Kernel standard deviation in frames; 0 returns the input unchanged.
    truncate : float
        Kernel radius in sigmas.
    min_support : float
        A frame that was invalid becomes valid when its valid neighbours carry at least this
        fraction of the kernel's mass inside the clip; valid frames stay valid.

    Returns
    -------
    smoothed : (T, ...) float64
        Smoothed values; where no valid sample lies within the kernel, the input value.
    valid_out : (T, ...) bool
        ``valid | support >= min_support``, the shape of ``valid``.
    """
    values = np.asarray(values, dtype=np.float64)
    mask = np.ones(values.shape[:1], bool) if valid is None else np.asarray(valid, bool)
    if values.shape[: mask.ndim] != mask.shape:
        raise ValueError(f"valid shape {mask.shape} does not lead values shape {values.shape}")
    kernel = gaussian_kernel(sigma, truncate=truncate)
    pad = min(len(kernel) // 2, len(values) - 1)
    values_ext, mask_ext = odd_reflection(values, pad), reflection_mask(mask, pad)
    weight = mask_ext.reshape(mask_ext.shape + (1,) * (values.ndim - mask.ndim)).astype(np.float64)
    # where(): an invalid sample may hold NaN, and NaN * 0 would spread it to its neighbours
    numerator = convolve1d(np.where(weight > 0, values_ext, 0.0), kernel, axis=0, mode="constant", cval=0.0)
    support = convolve1d(weight, kernel, axis=0, mode="constant", cval=0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        smoothed = np.where(support > 1e-12, numerator / np.maximum(support, 1e-300), values_ext)
    inner = slice(pad, pad + len(values))
    # validity from the clip's own samples: a reflection adds no evidence that a point was there
    weight = weight[inner]
    support = convolve1d(weight, kernel, axis=0, mode="constant", cval=0.0)
    in_clip = convolve1d(np.ones(len(values)), kernel, mode="constant", cval=0.0)
    support = support.reshape(mask.shape + (-1,))[..., 0] / in_clip.reshape((-1,) + (1,) * (mask.ndim - 1))
    return smoothed[inner], mask | (support >= min_support)


def odd_reflection(values: np.ndarray, pad: int) -> np.ndarray:
    """``(T, ...)`` -> ``(T + 2 pad, ...)``: ``pad`` samples before the first and after the last,
    ``x(-k) = 2 x(0) - x(k)`` and ``x(T-1+k) = 2 x(T-1) - x(T-1-k)``; ``pad <= T - 1``."""
    mirrored = np.arange(pad, 0, -1)  # k = pad .. 1
    head = 2.0 * values[:1] - values[mirrored]
    tail = 2.0 * values[-1:] - values[len(values) - 1 - mirrored[::-1]]
    return np.concatenate([head, values, tail])


def reflection_mask(mask: np.ndarray, pad: int) -> np.ndarray:
    """The validity of :func:`odd_reflection`'s samples: a reflected sample is valid where both the
    end sample and the sample it mirrors are."""
    mirrored = np.arange(pad, 0, -1)
    head = mask[:1] & mask[mirrored]
    tail = mask[-1:] & mask[len(mask) - 1 - mirrored[::-1]]
    return np.concatenate([head, mask, tail])


class GaussianSmooth(SequenceStage):
    """``smooth.gaussian``: each trajectory of a ``points`` bundle smoothed over time."""

    name = "smooth.gaussian"
    version = "2"
    doc = "Gaussian smoothing of point trajectories over time (normalized, mask-aware, odd reflection at the ends)"
    inputs = {"points": "points"}
    outputs = {"points": "points"}
    params = (
        Param("sigma", float, 1.5, "kernel standard deviation in frames (0 = off)"),
        Param("truncate", float, 3.0, "kernel radius in sigmas"),
        Param("min_support", float, 0.5, "kernel mass of valid neighbours that makes an invalid frame valid"),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        params = {p.name: p.default for p in self.params} | dict(params)
        bundle = dict(inputs["points"])
        sigma = float(params["sigma"])
        if sigma < 0:
            raise StageError(f"smooth.gaussian: parameter sigma must be >= 0, got {sigma}")
        xy, valid = gaussian_smooth(
            bundle["xy"], bundle["valid"], sigma=sigma, truncate=float(params["truncate"]),
            min_support=float(params["min_support"]),
        )
        bundle.update(xy=xy, valid=valid)
        return {"points": bundle}
