"""Image files for tests of the readers' bounds."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path


def big_png(path: Path, width: int, height: int) -> None:
    """Write a valid 1-bit grey PNG of ``width`` x ``height`` px (all black): a few kB on disk
    for millions of pixels, as a decompression bomb is."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    packer = zlib.compressobj(9)
    row = b"\0" * (1 + (width + 7) // 8)
    body = b"".join(packer.compress(row) for _ in range(height)) + packer.flush()
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 1, 0, 0, 0, 0))
        + chunk(b"IDAT", body)
        + chunk(b"IEND", b"")
    )
