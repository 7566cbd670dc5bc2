"""sRGB <-> scene-linear conversions (IEC 61966-2-1) and 8-bit quantization.

One implementation serves numpy arrays and torch tensors: the array namespace is picked from the
argument's type, and the result keeps the argument's type, dtype and device. torch is never
imported by this module; a tensor can only exist if the caller imported it.

The sRGB transfer function (IEC 61966-2-1:1999, the piecewise curve):

    linear = srgb / 12.92                        if srgb <= 0.04045
           = ((srgb + 0.055) / 1.055) ** 2.4     otherwise

    srgb   = 12.92 * linear                      if linear <= 0.0031308
           = 1.055 * linear ** (1 / 2.4) - 0.055 otherwise

Values outside [0, 1] are not clipped: negatives follow the linear segment, values above 1 the
power segment, so the conversions are inverse to each other on the whole real line.
"""

from __future__ import annotations

import sys
from types import ModuleType
from typing import TypeVar

import numpy as np

Array = TypeVar("Array")  # numpy.ndarray or torch.Tensor

SRGB_THRESHOLD = 0.04045  # encoded value where the curve changes segment
LINEAR_THRESHOLD = 0.0031308  # the same break point on the linear side (0.04045 / 12.92)


def _namespace(x: object) -> ModuleType:
    """``torch`` for a torch tensor, ``numpy`` otherwise (without importing torch)."""
    torch = sys.modules.get("torch")
    if torch is not None and isinstance(x, torch.Tensor):
        return torch
    return np


def srgb_to_linear(srgb: Array) -> Array:
    """Decode sRGB-encoded values to scene-linear (IEC 61966-2-1 electro-optical curve).

    Parameters
    ----------
    srgb : numpy.ndarray or torch.Tensor, any shape, floating point
        sRGB-encoded values, nominally in [0, 1].

    Returns
    -------
    Same type, shape, dtype (and device) as ``srgb``: linear-light values.
    """
    xp = _namespace(srgb)
    if xp is np:
        srgb = np.asarray(srgb)
    power = ((xp.clip(srgb, SRGB_THRESHOLD, None) + 0.055) / 1.055) ** 2.4
    return xp.where(srgb <= SRGB_THRESHOLD, srgb / 12.92, power)


def linear_to_srgb(linear: Array) -> Array:
    """Encode scene-linear values as sRGB (inverse of :func:`srgb_to_linear`).

    Parameters
    ----------
    linear : numpy.ndarray or torch.Tensor, any shape, floating point
        Linear-light values, nominally in [0, 1].

    Returns
    -------
    Same type, shape, dtype (and device) as ``linear``: sRGB-encoded values.
    """
    xp = _namespace(linear)
    if xp is np:
        linear = np.asarray(linear)
    power = 1.055 * xp.clip(linear, LINEAR_THRESHOLD, None) ** (1 / 2.4) - 0.055
    return xp.where(linear <= LINEAR_THRESHOLD, linear * 12.92, power)


def to_unit_float(image: Array) -> Array:
    """Integer images as float32 in [0, 1] (``uint8 / 255``); floating images unchanged.

    Parameters
    ----------
    image : numpy.ndarray or torch.Tensor, any shape, uint8 or floating point.
    """
    xp = _namespace(image)
    if image.dtype == xp.uint8:
        return image.to(xp.float32) / 255.0 if xp is not np else image.astype(np.float32) / 255.0
    return image


def to_uint8(image: Array) -> Array:
    """Encoded float images in [0, 1] to uint8 (clipped, rounded to nearest); uint8 unchanged.

    Parameters
    ----------
    image : numpy.ndarray or torch.Tensor, any shape, uint8 or floating point
        Display-encoded (sRGB) values; apply :func:`linear_to_srgb` first to linear data.
    """
    xp = _namespace(image)
    if image.dtype == xp.uint8:
        return image
    if xp is np:
        image = image.astype(np.float32, copy=False)  # float16 has too few bits for x 255
    scaled = xp.round(xp.clip(image, 0.0, 1.0) * 255.0)
    return scaled.to(xp.uint8) if xp is not np else scaled.astype(np.uint8)
