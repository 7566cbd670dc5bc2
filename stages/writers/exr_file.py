"""OpenEXR scanline files in numpy and zlib-ng's deflate: the ``none``, ``zips`` and ``zip`` codecs.

The file layout is OpenEXR's public one (openexr.com, "OpenEXR File Layout"): the magic number
20000630, the version field (2, plus the long-names flag 0x400 when a name is longer than 31
bytes), the header (attributes ``name\\0 type\\0 int32 size value``, sorted by name as OpenEXR
writes them, then a null byte), the line offset table (one uint64 file offset per chunk), then
the chunks ``int32 y, int32 size, data``. All numbers are little-endian.

A chunk holds ``LINES_PER_CHUNK[compression]`` scanlines (the last one may hold fewer); each
scanline holds every channel in turn, the channels sorted by name, each as ``width`` values.
``zip`` (16 lines) and ``zips`` (1 line) pass the chunk through OpenEXR's ZIP preprocessing
(``ImfZip.cpp``: the bytes of even index, then those of odd index, then a delta predictor
``d[i] = (b[i] - b[i-1] + 128) mod 256``) and a zlib stream (RFC 1950) made by zlib-ng (the
``zlib-ng`` package, pinned: zlib's format and API, deflate's speed close to ISA-L's: level 1 is
zlib-ng's "quick" strategy, 3x faster than zlib's level 1 for files ~9 % larger); a chunk that
deflate does not shrink is stored raw, as OpenEXR does (a reader tells them apart by the size).
The bytes are a function of the pixels, the attributes, the codec and the level, for one zlib-ng
release (another release may deflate the same bytes differently; the pixels stay the same).

Not ISA-L's deflate (``isal``, used before): its level-1 output depends on the address of its
stream state, which python-isal keeps on the calling thread's C stack, so the same chunk could
come out as other, equally valid bytes in another thread or process (``docs/writers.md``,
"Deterministic bytes"); zlib-ng's depends on the bytes and the level only (the same tests).

Header attributes are typed as OpenImageIO 3.2 writes them (``exroutput.cpp``), so a file of this
module and one of OpenImageIO carry the same header bytes: Python ``int`` -> ``int``, ``float``
-> ``float``, ``str`` -> ``string``, a tuple of n floats -> ``v2f`` (n = 2), ``v3f`` (3), ``m33f``
(9, row-major), ``m44f`` (16), else ``floatvector``.
"""

from __future__ import annotations

import functools
import struct
from collections.abc import Mapping
from typing import BinaryIO

import numpy as np
from zlib_ng import zlib_ng

Attribute = int | float | str | tuple[float, ...]
MAGIC = 20000630
VERSION = 2
LONG_NAMES = 0x400  # version flag: some attribute or type name is longer than 31 bytes
COMPRESSION_CODES = {"none": 0, "zips": 2, "zip": 3}  # OpenEXR's Compression enum
LINES_PER_CHUNK = {"none": 1, "zips": 1, "zip": 16}
ZIP_LEVELS = range(1, 10)  # zlib's deflate levels (0 would only store: the raw chunk is smaller)
ZIP_LEVEL = 1  # default: the cheapest (docs/writers.md, "Zip level")
PIXEL_TYPES = {np.dtype(np.float16): 1, np.dtype(np.float32): 2}  # HALF, FLOAT (UINT not used)
FLOAT_TUPLE_TYPES = {2: "v2f", 3: "v3f", 9: "m33f", 16: "m44f"}  # else "floatvector"


def _attribute(name: str, type_name: str, value: bytes) -> bytes:
    return b"%s\0%s\0%s%s" % (name.encode(), type_name.encode(), struct.pack("<i", len(value)), value)


def typed_attribute(name: str, value: Attribute) -> bytes:
    """One header attribute ``name\\0 type\\0 size value`` for a Python value (module docstring).

    Raises
    ------
    TypeError
        ``value`` is not an int, float, str or tuple of numbers (``bool`` is not accepted: say
        ``int(flag)``).
    """
    if isinstance(value, bool) or not isinstance(value, int | float | str | tuple):
        raise TypeError(f"EXR attribute {name!r}: expected int, float, str or tuple of floats, got {type(value).__name__}")
    if isinstance(value, int):
        return _attribute(name, "int", struct.pack("<i", value))
    if isinstance(value, float):
        return _attribute(name, "float", struct.pack("<f", value))
    if isinstance(value, str):
        return _attribute(name, "string", value.encode())
    floats = np.asarray(value, "<f4")
    return _attribute(name, FLOAT_TUPLE_TYPES.get(len(floats), "floatvector"), floats.tobytes())


def header_bytes(
    width: int,
    height: int,
    *,
    channels: Mapping[str, np.dtype],
    compression: str,
    attributes: Mapping[str, Attribute],
) -> bytes:
    """Magic number, version and header of a scanline file, up to and including its null byte.

    Parameters
    ----------
    width, height : image size in px (data window = display window = (0, 0)..(width-1, height-1)).
    channels : channel name -> dtype (float16 or float32), any order (written sorted by name).
    compression : a key of ``COMPRESSION_CODES``.
    attributes : extra attributes (module docstring for their types); they may not replace the
        required ones written here.
    """
    box = struct.pack("<4i", 0, 0, width - 1, height - 1)
    chlist = (
        b"".join(
            name.encode() + b"\0" + struct.pack("<iB3xii", PIXEL_TYPES[np.dtype(dtype)], 0, 1, 1)
            for name, dtype in sorted(channels.items())
        )
        + b"\0"
    )
    required = {
        "channels": ("chlist", chlist),
        "compression": ("compression", bytes([COMPRESSION_CODES[compression]])),
        "dataWindow": ("box2i", box),
        "displayWindow": ("box2i", box),
        "lineOrder": ("lineOrder", b"\0"),  # INCREASING_Y
        "pixelAspectRatio": ("float", struct.pack("<f", 1.0)),
        "screenWindowCenter": ("v2f", struct.pack("<2f", 0.0, 0.0)),
        "screenWindowWidth": ("float", struct.pack("<f", 1.0)),
    }
    clash = sorted(required.keys() & attributes.keys())
    if clash:
        raise ValueError(f"EXR attributes: expected extra names, got the required {clash}")
    encoded = {name: _attribute(name, *typed) for name, typed in required.items()}
    encoded |= {name: typed_attribute(name, value) for name, value in attributes.items()}
    long_names = any(len(name.encode()) > 31 for name in encoded)
    version = VERSION | (LONG_NAMES if long_names else 0)
    body = b"".join(encoded[name] for name in sorted(encoded, key=str.encode))
    return struct.pack("<ii", MAGIC, version) + body + b"\0"


def scanlines(channels: Mapping[str, np.ndarray]) -> np.ndarray:
    """The uncompressed scanlines: ``(H, line bytes)`` uint8, each row the channels sorted by name.

    Parameters
    ----------
    channels : name -> ``(H, W)`` float16 or float32 array (any strides), all of one size.
    """
    shapes = {np.shape(c) for c in channels.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ValueError(f"EXR channels: expected (H, W) arrays of one size, got shapes {sorted(shapes)}")
    height, width = shapes.pop()
    names = sorted(channels)
    sizes = [width * np.dtype(channels[n].dtype).itemsize for n in names]
    lines = np.empty((height, sum(sizes)), np.uint8)
    offset = 0
    for name, size in zip(names, sizes):
        channel = channels[name]
        if channel.dtype not in PIXEL_TYPES:
            raise TypeError(f"EXR channel {name!r}: expected float16 or float32, got {channel.dtype}")
        lines[:, offset : offset + size].view(channel.dtype)[:] = channel
        offset += size
    return lines


def zip_predictor(blocks: np.ndarray) -> np.ndarray:
    """OpenEXR's ZIP preprocessing of each row of ``blocks`` ``(n, B)`` uint8, B even.

    Per row: the bytes of even index, then those of odd index; then every byte but the first
    replaced by its difference to the one before plus 128, modulo 256 (``ImfZip.cpp``).
    """
    n, size = blocks.shape
    split = np.ascontiguousarray(blocks.reshape(n, size // 2, 2).transpose(0, 2, 1)).reshape(n, size)
    out = np.empty_like(split)
    out[:, 0] = split[:, 0]
    np.subtract(split[:, 1:], split[:, :-1], out=out[:, 1:])  # uint8 arithmetic wraps modulo 256
    out[:, 1:] += 128
    return out


@functools.lru_cache(maxsize=16)
def zero_block_data(size: int, level: int) -> bytes:
    """The ``zip`` chunk data of a block of ``size`` zero bytes: the zlib stream of its
    preprocessed bytes (0, then 128 ``size - 1`` times), or the raw block if that is not smaller."""
    packed = zlib_ng.compress(zip_predictor(np.zeros((1, size), np.uint8))[0], level)
    return packed if len(packed) < size else bytes(size)


def _compress_blocks(blocks: np.ndarray, level: int) -> list[bytes | np.ndarray]:
    """``zip`` chunk data of each row of ``blocks`` ``(n, B)`` uint8.

    All-zero blocks before the first and after the last block holding a non-zero byte (the
    rows above and below the face in a premultiplied frame) take the data of
    :func:`zero_block_data`, the same bytes as preprocessing and compressing each of them.
    """
    nonzero = np.flatnonzero(blocks.any(axis=1))
    first, last = (nonzero[0], nonzero[-1] + 1) if nonzero.size else (0, 0)
    zero = zero_block_data(blocks.shape[1], level)
    chunks: list[bytes | np.ndarray] = [zero] * first
    for block, predicted in zip(blocks[first:last], zip_predictor(blocks[first:last])):
        packed = zlib_ng.compress(predicted, level)
        chunks.append(packed if len(packed) < len(block) else block)
    return chunks + [zero] * (len(blocks) - last)


def chunk_data(lines: np.ndarray, *, compression: str, level: int) -> list[bytes | np.ndarray]:
    """The data of every chunk of ``lines`` (from :func:`scanlines`), in file order.

    ``zip``/``zips`` chunks are zlib streams at ``level`` (``ZIP_LEVELS``) of the preprocessed block, or the
    raw block where that is not smaller; ``none`` chunks are the raw lines.
    """
    height, line_bytes = lines.shape
    per_chunk = LINES_PER_CHUNK[compression]
    if compression == "none":
        return list(lines)
    full = height // per_chunk * per_chunk
    raw = [lines[:full].reshape(-1, per_chunk * line_bytes)]
    if full < height:
        raw.append(lines[full:].reshape(1, -1))
    return [chunk for blocks in raw for chunk in _compress_blocks(blocks, level)]


def write_scanline_exr(
    file: BinaryIO,
    channels: Mapping[str, np.ndarray],
    *,
    attributes: Mapping[str, Attribute],
    compression: str = "zip",
    level: int = ZIP_LEVEL,
) -> None:
    """Write a single-part scanline OpenEXR file to the open binary ``file``.

    Parameters
    ----------
    file : binary file object, written from its current position (which must be 0: the offset
        table holds absolute offsets).
    channels : name -> ``(H, W)`` float16 (``HALF``) or float32 (``FLOAT``) pixels, row 0 at the
        top (``INCREASING_Y``).
    attributes : extra header attributes (module docstring for their EXR types).
    compression : ``none``, ``zips`` or ``zip``.
    level : zlib deflate level (``ZIP_LEVELS``: 1 fastest .. 9 smallest) for ``zips`` / ``zip``.
    """
    if compression not in COMPRESSION_CODES:
        raise ValueError(f"EXR compression: expected one of {sorted(COMPRESSION_CODES)}, got {compression!r}")
    if level not in ZIP_LEVELS:
        raise ValueError(f"EXR zip level: expected {ZIP_LEVELS.start}..{ZIP_LEVELS.stop - 1}, got {level}")
    lines = scanlines(channels)
    height, width = lines.shape[0], next(iter(channels.values())).shape[1]
    dtypes = {name: channel.dtype for name, channel in channels.items()}
    header = header_bytes(width, height, channels=dtypes, compression=compression, attributes=attributes)
    chunks = chunk_data(lines, compression=compression, level=level)
    sizes = np.array([len(c) if isinstance(c, bytes) else c.nbytes for c in chunks], np.int64)
    table_end = len(header) + 8 * len(chunks)
    offsets = table_end + np.concatenate([[0], np.cumsum(sizes + 8)[:-1]])
    per_chunk = LINES_PER_CHUNK[compression]
    parts = [header, offsets.astype("<u8").tobytes()]
    for index, (chunk, size) in enumerate(zip(chunks, sizes)):
        parts += [struct.pack("<ii", index * per_chunk, size), chunk]
    file.write(b"".join(parts))  # one write: 800 small ones cost more for ``none``
