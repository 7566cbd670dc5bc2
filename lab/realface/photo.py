"""The source photo: the face of scikit-image's public-domain astronaut portrait, cropped and upscaled.

``skimage.data.astronaut()`` is 512 x 512 RGB with a small face (about 60 px between the outer
eye corners). :data:`CROP` is a square around the face (hair to chin, some neck); it is resized
to ``size x size`` with ``cv2.INTER_LANCZOS4``. Pixel coordinates (origin at the centre of the
top-left pixel) map as ``x_astronaut = x0 + (x + 0.5) * side / size - 0.5`` (OpenCV's resize
alignment), the same for y.
"""

from __future__ import annotations

import cv2
import numpy as np

CROP = (125, 20, 200)
"""``(x0, y0, side)`` px of the square crop in the astronaut image (its top-left pixel's corner)."""


def source_photo(size: int) -> np.ndarray:
    """The cropped, upscaled portrait.

    Parameters
    ----------
    size
        Output side in px (a positive even number: H.264 4:2:0 frames need even sizes).

    Returns
    -------
    numpy.ndarray
        ``(size, size, 3)`` uint8 RGB.
    """
    if not isinstance(size, (int, np.integer)) or isinstance(size, bool):
        raise TypeError(f"size: expected an int, got {type(size).__name__}")
    if size <= 0 or size % 2:
        raise ValueError(f"size: expected a positive even number of px, got {size}")
    from skimage.data import astronaut

    x0, y0, side = CROP
    crop = astronaut()[y0 : y0 + side, x0 : x0 + side]
    return cv2.resize(crop, (int(size), int(size)), interpolation=cv2.INTER_LANCZOS4)
