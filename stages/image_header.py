"""An image file's size from its header, checked against a pixel limit before anything is decoded.

OpenCV allocates the whole image a file's header declares when it decodes it (up to 2^30
pixels by default): a 2.6 MB PNG declaring 30000x30000 pixels takes 102 s and 5.5 GB. Readers of
user images (a photo folder, a pack's images) call :func:`image_size` first, with their limit.
Pillow reads the header only (``Image.open`` is lazy) of PNG, JPEG, TIFF and WebP files.
"""

from __future__ import annotations

import warnings
from pathlib import Path


class ImageTooLarge(ValueError):
    """An image file's header declares more pixels than the reader allows; the message says
    how many (``"30000x30000 px"``) and the limit."""


def image_size(path: str | Path, *, max_pixels: int, verify: bool = False) -> tuple[int, int] | None:
    """``(width, height)`` in px as stored in the header of image file ``path`` (before any
    EXIF rotation), or None when it is not an image file whose header Pillow reads. With
    ``verify``, a PNG's chunks are also checked (Pillow's ``verify``: their CRCs, a truncated
    file) and a damaged one gives None: libpng prints its own ``libpng error:`` line on the
    process's stderr when OpenCV decodes it.

    Raises
    ------
    ImageTooLarge
        The header declares more than ``max_pixels`` pixels (Pillow itself refuses to open a
        header of more than twice ``PIL.Image.MAX_IMAGE_PIXELS``, ~179 million: reported so).
    """
    from PIL import Image, UnidentifiedImageError

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # the limit here is the caller's
            with Image.open(path) as image:
                width, height = int(image.size[0]), int(image.size[1])
                if verify and image.format == "PNG" and width * height <= max_pixels:
                    image.verify()
    except Image.DecompressionBombError:
        raise ImageTooLarge(f"more than {2 * Image.MAX_IMAGE_PIXELS} px, the limit is {max_pixels} px") from None
    except (OSError, UnidentifiedImageError, ValueError, SyntaxError):
        return None
    if width * height > max_pixels:
        raise ImageTooLarge(f"{width}x{height} px, more than the {max_pixels} px allowed")
    return width, height
