"""Image files for tests of the readers' bounds."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np


def big_png(path: Path, width: int, height: int) -> None:
    """Write a valid 1-bit grey PNG of ``width`` x ``height`` px (all black): a few kB on disk
    for millions of pixels, as a decompression bomb is."""

    packer = zlib.compressobj(9)
    row = b"\0" * (1 + (width + 7) // 8)
    body = b"".join(packer.compress(row) for _ in range(height)) + packer.flush()
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 1, 0, 0, 0, 0))
        + _chunk(b"IDAT", body)
        + _chunk(b"IEND", b"")
    )


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def rgb_png(path: Path, rgb: np.ndarray, *, interlaced: bool = False, extra: bytes = b"", after_end: bytes = b"") -> None:
    """Write ``rgb (H, W, 3)`` uint8 as an 8-bit RGB PNG (rows unfiltered; ``interlaced``:
    Adam7), with ``extra`` raw bytes inflated after the image's rows (libpng: "Too much image
    data") and ``after_end`` compressed bytes after the zlib stream's end ("Extra compressed
    data"); with neither, a valid file."""
    h, w = rgb.shape[:2]
    passes = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))
    rows = [row for x0, y0, dx, dy in (passes if interlaced else ((0, 0, 1, 1),)) for row in rgb[y0::dy, x0::dx] if row.size]
    raw = b"".join(b"\0" + row.tobytes() for row in rows) + extra
    header = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, int(interlaced))
    body = zlib.compress(raw) + after_end
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", header) + _chunk(b"IDAT", body) + _chunk(b"IEND", b""))
