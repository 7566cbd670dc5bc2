"""sRGB <-> scene-linear conversions (IEC 61966-2-1), 8-bit quantization, and grey (luma).

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

Grey is BT.601 luma of the encoded values, ``Y = 0.299 R + 0.587 G + 0.114 B``, two ways that do
not give the same numbers, each kept for the stages that use it: :func:`luma_opencv` (OpenCV's
``COLOR_RGB2GRAY``: for uint8 in 15-bit fixed point, rounded, uint8 out) and
:func:`luma_float32` (the weights as float32, no rounding). Both are numpy only.
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
    if xp is np and image.dtype == np.float16 and image.size:
        return _half_to_uint8(image)
    if xp is np:
        image = image.astype(np.float32, copy=False)  # float16 has too few bits for x 255
    scaled = xp.round(xp.clip(image, 0.0, 1.0) * 255.0)
    return scaled.to(xp.uint8) if xp is not np else scaled.astype(np.uint8)


BT601_LUMA = (0.299, 0.587, 0.114)  # Rec. ITU-R BT.601 Kr, 1 - Kr - Kb, Kb


def luma_opencv(rgb: np.ndarray) -> np.ndarray:
    """OpenCV's BT.601 luma (``cv2.cvtColor(..., COLOR_RGB2GRAY)``) of RGB images.

    ``rgb (..., W, 3)`` uint8 or float32 -> ``(..., W)`` of the same dtype; uint8 is computed in
    15-bit fixed point, ``(9798 R + 19235 G + 3735 B + 2^14) >> 15``. The leading axes are passed
    to OpenCV as rows of one image ``(-1, W, 3)``.
    """
    import cv2

    rgb = np.ascontiguousarray(rgb)
    if rgb.ndim < 2 or rgb.shape[-1] != 3:
        raise ValueError(f"expected RGB images (..., W, 3), got {rgb.shape}")
    gray = cv2.cvtColor(rgb.reshape(-1, rgb.shape[-2], 3), cv2.COLOR_RGB2GRAY)
    return gray.reshape(rgb.shape[:-1])


def luma_float32(rgb: np.ndarray) -> np.ndarray:
    """BT.601 luma ``(...)`` float32 of RGB values ``(..., 3)`` (any dtype, cast to float32), in
    their own units: ``rgb @ (0.299, 0.587, 0.114)`` in float32, not rounded."""
    return np.asarray(rgb, np.float32) @ np.array(BT601_LUMA, np.float32)


HALF_INF_BITS = 0x7C00  # +inf as a float16 bit pattern


def _half_to_uint8(image: np.ndarray) -> np.ndarray:
    """:func:`to_uint8` of a non-empty float16 ndarray, by OpenCV's saturating multiply.

    ``x * 255`` is exact in float32 for every half float (11 + 8 significant bits), and OpenCV
    converts it to uint8 as ``to_uint8`` does: rounded to nearest (ties to even, as ``np.round``),
    saturated to 0..255 (the clip), NaN -> 0 (numpy's cast on x86). Its one difference, +inf -> 0,
    is set to 255 afterwards. All 65536 half floats give ``to_uint8``'s float32 values
    (tests/stages/test_color.py); one SIMD pass instead of numpy's float16 -> float32 conversion
    (5 to 8 times less CPU on a 600x800 frame).
    """
    import cv2

    flat = np.ascontiguousarray(image).reshape(1, -1)
    out = cv2.multiply(flat, 255.0, dtype=cv2.CV_8U)
    cv2.bitwise_or(out, cv2.compare(flat.view(np.uint16), HALF_INF_BITS, cv2.CMP_EQ), dst=out)
    return out.reshape(image.shape)


# Rec. ITU-R BT.601-7 R'G'B' -> Y'CbCr at 8 bits, limited ("studio") range, as a 3x4 affine map of
# uint8 values: with Kr = 0.299, Kb = 0.114 (E'y = Kr E'r + (1 - Kr - Kb) E'g + Kb E'b),
#   Y' = 16 + 219 E'y,   Cb = 128 + 224 (E'b - E'y) / 1.772,   Cr = 128 + 224 (E'r - E'y) / 1.402,
# E' = value / 255 (sections 2.5.1-2.5.4 of the Recommendation; swscale's and OpenCV's matrix).
BT601_LIMITED = (
    np.array([[65.481, 128.553, 24.966, 16 * 255], [-37.797, -74.203, 112.0, 128 * 255], [112.0, -93.786, -18.214, 128 * 255]])
    / 255
)


def rgb_to_ycbcr420(
    image: np.ndarray, *, out: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """8-bit R'G'B' to planar Y'CbCr 4:2:0, BT.601 limited range (``BT601_LIMITED``).

    Y' is the matrix applied to each pixel; Cb and Cr of each 2x2 block the matrix applied to the
    block's mean colour (chroma sited between the four pixels; OpenCV's own ``COLOR_RGB2YUV_I420``
    takes the top-left pixel's, which aliases at edges). Rounded to nearest; OpenCV calls only,
    each releasing the GIL.

    Parameters
    ----------
    image : numpy.ndarray, (H, W, 3) uint8 RGB, or (H, W, 1) / (H, W) uint8 gray (R = G = B)
        H and W even.
    out : (Y', Cb, Cr) uint8 arrays of shapes (H, W), (H / 2, W / 2), (H / 2, W / 2), optional
        Filled in place; rows may be strided (an FFmpeg frame's planes, whose lines are padded).

    Returns
    -------
    (Y', Cb, Cr) : the ``out`` arrays, or new ones of those shapes.
    """
    import cv2

    if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
        raise TypeError(f"rgb_to_ycbcr420: expected a uint8 ndarray, got {type(image).__name__} {getattr(image, 'dtype', '')}")
    if (
        image.ndim not in (2, 3)
        or image.ndim == 3
        and image.shape[2] not in (1, 3)
        or image.shape[0] % 2
        or image.shape[1] % 2
        or not image.size
    ):
        raise ValueError(f"rgb_to_ycbcr420: expected (H, W, 3), (H, W, 1) or (H, W) with H, W even and > 0, got {image.shape}")
    height, width = image.shape[:2]
    shapes = ((height, width), (height // 2, width // 2), (height // 2, width // 2))
    if out is None:
        out = tuple(np.empty(shape, np.uint8) for shape in shapes)
    elif tuple(plane.shape for plane in out) != shapes or any(plane.dtype != np.uint8 for plane in out):
        raise ValueError(
            f"rgb_to_ycbcr420: expected out planes {shapes} uint8, got {[(plane.shape, plane.dtype.name) for plane in out]}"
        )
    if image.ndim == 2 or image.shape[2] == 1:
        image = cv2.cvtColor(image.reshape(height, width), cv2.COLOR_GRAY2RGB)
    # All three rows of the matrix each time: OpenCV's SIMD path (3 -> 1 or 2 channels is not).
    full = cv2.transform(image, BT601_LIMITED)
    mean = cv2.transform(cv2.resize(image, shapes[1][::-1], interpolation=cv2.INTER_AREA), BT601_LIMITED)
    cv2.mixChannels([full], [out[0]], [0, 0])
    cv2.mixChannels([mean], [out[1], out[2]], [1, 0, 2, 1])
    return out
