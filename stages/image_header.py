"""An image file's size from its header, checked against a pixel limit before anything is decoded.

OpenCV allocates the whole image a file's header declares when it decodes it (up to 2^30
pixels by default): a 2.6 MB PNG declaring 30000x30000 pixels takes 102 s and 5.5 GB. Readers of
user images (a photo folder, a pack's images) call :func:`image_size` first, with their limit.
Pillow reads the header only (``Image.open`` is lazy) of PNG, JPEG, TIFF and WebP files.
"""

from __future__ import annotations

import struct
import warnings
import zlib
from pathlib import Path

from runner.files import open_regular

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_SAMPLES = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # colour type -> samples per pixel
_ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))  # x0, y0, dx, dy
_INFLATE_STEP = 1 << 20  # bytes inflated at a time while counting


class ImageTooLarge(ValueError):
    """An image file's header declares more pixels than the reader allows; the message says
    how many (``"30000x30000 px"``) and the limit."""


def image_size(path: str | Path, *, max_pixels: int, verify: bool = False) -> tuple[int, int] | None:
    """``(width, height)`` in px as stored in the header of image file ``path`` (before any
    EXIF rotation), or None when it is not an image file whose header Pillow reads. With
    ``verify``, a PNG's chunks are also checked (Pillow's ``verify``: their CRCs, a truncated
    file) and so is its image data (:func:`png_data_whole`); a damaged one gives None: libpng
    prints its own ``libpng error:`` or ``libpng warning:`` line on the process's stderr when
    OpenCV decodes it.

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
                    if not png_data_whole(path):
                        return None
    except Image.DecompressionBombError:
        raise ImageTooLarge(f"more than {2 * Image.MAX_IMAGE_PIXELS} px, the limit is {max_pixels} px") from None
    except (OSError, UnidentifiedImageError, ValueError, SyntaxError):
        return None
    if width * height > max_pixels:
        raise ImageTooLarge(f"{width}x{height} px, more than the {max_pixels} px allowed")
    return width, height


def png_data_bytes(width: int, height: int, depth: int, colour: int, interlaced: bool) -> int:
    """Bytes of a PNG's inflated image data as its IHDR declares it: per row of each pass
    (one pass, or Adam7's seven when ``interlaced``) a filter byte and the row's packed samples
    (``depth`` bits each, :data:`_PNG_SAMPLES` per pixel of colour type ``colour``)."""
    bits = _PNG_SAMPLES[colour] * depth
    total = 0
    for x0, y0, dx, dy in _ADAM7 if interlaced else ((0, 0, 1, 1),):
        columns, rows = (width - x0 + dx - 1) // dx, (height - y0 + dy - 1) // dy
        if columns > 0 and rows > 0:
            total += rows * (1 + (columns * bits + 7) // 8)
    return total


def png_data_whole(path: str | Path) -> bool:
    """Whether the IDAT chunks of PNG file ``path`` hold one zlib stream that inflates to
    exactly the bytes its IHDR declares (:func:`png_data_bytes`), with nothing after the
    stream's end. libpng decodes a file with extra data anyway, printing ``libpng warning:
    IDAT: Extra compressed data`` or ``Too much image data``. Inflated in steps of
    :data:`_INFLATE_STEP` bytes, counted, not kept."""
    inflate = zlib.decompressobj()
    count, expected = 0, None
    try:
        with open_regular(path) as f:
            if f.read(8) != _PNG_SIGNATURE:
                return False
            while header := f.read(8):
                length, kind = struct.unpack(">I4s", header)
                data = f.read(length)
                f.read(4)  # the CRC, checked by Pillow's verify
                if kind == b"IHDR":
                    width, height, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", data[:13])
                    expected = png_data_bytes(width, height, depth, colour, interlace == 1)
                elif kind == b"IDAT":
                    if inflate.eof:
                        return False  # compressed data after the stream's end
                    while data and not inflate.eof:
                        count += len(inflate.decompress(data, _INFLATE_STEP))
                        data = inflate.unconsumed_tail
                    if inflate.unused_data or (expected is not None and count > expected):
                        return False
                elif kind == b"IEND":
                    break
    except (OSError, KeyError, struct.error, zlib.error):
        return False
    return inflate.eof and count == expected
