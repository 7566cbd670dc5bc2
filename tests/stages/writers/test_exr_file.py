"""The numpy + zlib-ng OpenEXR writer against two independent implementations: OpenImageIO (reads
the files, writes the reference headers) and the official OpenEXR binding (reads the files)."""

import io
import struct
import zlib
from pathlib import Path

import numpy as np
import OpenEXR
import OpenImageIO as oiio
import pytest
from zlib_ng import zlib_ng

from stages.writers.exr import COLOR_SPACE, oiio_write_exr
from stages.writers.exr_file import (
    LINES_PER_CHUNK,
    ZIP_LEVEL,
    ZIP_LEVELS,
    chunk_data,
    header_bytes,
    scanlines,
    write_scanline_exr,
    zero_block_data,
    zip_predictor,
)

ATTRIBUTES = {
    "exmap:frame": 12,
    "exmap:time_s": 0.4,
    "exmap:fps": 30.0,
    "exmap:name": "take 3",
    "exmap:one": (1.5,),
    "exmap:two": (1.0, -2.0),
    "exmap:pose_rvec": (0.1, -0.2, 0.3),
    "exmap:similarity": (1.0, 0.5, -3.25, 7.0),
    "exmap:six": tuple(np.linspace(-1, 1, 6)),
    "exmap:head_R": tuple(np.arange(9) / 7),
    "exmap:m44": tuple(np.arange(16) * 0.25),
}
OPENEXR_CODES = {"none": OpenEXR.NO_COMPRESSION, "zips": OpenEXR.ZIPS_COMPRESSION, "zip": OpenEXR.ZIP_COMPRESSION}
ALL_HALVES = np.arange(1 << 16, dtype=np.uint16).view(np.float16)  # inf, NaN and subnormals too


def _rgba(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """(H, W, 4) float16: smooth content (compressible), with every half bit pattern mixed in."""
    y, x = np.mgrid[0:height, 0:width]
    rgba = np.stack([np.sin(x / 7 + c) * np.cos(y / 5) for c in range(4)], axis=2).astype(np.float16)
    flat = rgba.reshape(-1)
    picks = rng.choice(flat.size, size=min(flat.size // 3, 1 << 16), replace=False)
    flat[picks] = rng.choice(ALL_HALVES, size=picks.size)
    return rgba


def _write(path: Path, rgba: np.ndarray, depth: np.ndarray | None = None, **options) -> None:
    channels = {name: rgba[..., c] for c, name in enumerate("RGBA")}
    if depth is not None:
        channels["Z"] = depth
    with open(path, "wb") as file:
        write_scanline_exr(file, channels, attributes={"colorInteropID": COLOR_SPACE, **ATTRIBUTES}, **options)


def _oiio_read(path: Path, pixel_type: oiio.TypeDesc = oiio.HALF) -> tuple[np.ndarray, oiio.ImageSpec]:
    inp = oiio.ImageInput.open(str(path))
    assert inp is not None, oiio.geterror()
    pixels, spec = inp.read_image(pixel_type), inp.spec()
    assert not inp.has_error, inp.geterror()
    inp.close()
    return pixels, spec


def _chunk_sizes(data: bytes, header_size: int, chunks: int) -> list[int]:
    offsets = np.frombuffer(data, "<u8", count=chunks, offset=header_size)
    return [struct.unpack_from("<ii", data, int(offset))[1] for offset in offsets]


@pytest.mark.parametrize("compression", ["none", "zips", "zip"])
@pytest.mark.parametrize("size", [(37, 23), (16, 1), (1, 5), (1, 1), (40, 16)])
def test_both_readers_give_back_the_halves_bit_for_bit(tmp_path: Path, compression: str, size: tuple) -> None:
    height, width = size
    rng = np.random.default_rng(height * 100 + width)
    rgba = _rgba(rng, height, width)
    path = tmp_path / "frame.exr"
    _write(path, rgba, compression=compression)
    pixels, spec = _oiio_read(path)
    assert (spec.width, spec.height, spec.format) == (width, height, oiio.TypeDesc("half"))
    assert spec.channelnames == ("R", "G", "B", "A")
    np.testing.assert_array_equal(pixels.view(np.uint16), rgba.view(np.uint16))
    with OpenEXR.File(str(path)) as exr:
        interleaved = exr.channels()["RGBA"].pixels
        assert exr.header()["compression"] == OPENEXR_CODES[compression]
    assert interleaved.dtype == np.float16
    np.testing.assert_array_equal(interleaved.view(np.uint16), rgba.view(np.uint16))


@pytest.mark.parametrize("compression", ["none", "zip"])
def test_float_depth_channel_is_exact(tmp_path: Path, compression: str) -> None:
    rng = np.random.default_rng(7)
    rgba = _rgba(rng, 21, 9)
    depth = (rng.random((21, 9), dtype=np.float32) * 1000).astype(np.float32)
    depth[3:5, 2:7] = np.inf
    path = tmp_path / "depth.exr"
    _write(path, rgba, depth, compression=compression)
    pixels, spec = _oiio_read(path, oiio.FLOAT)
    assert spec.channelnames == ("R", "G", "B", "A", "Z")
    assert spec.channelformats == (oiio.TypeDesc("half"),) * 4 + (oiio.TypeDesc("float"),)
    with OpenEXR.File(str(path), separate_channels=True) as exr:
        z = exr.channels()["Z"].pixels
    assert z.dtype == np.float32
    np.testing.assert_array_equal(z.view(np.uint32), depth.view(np.uint32))
    np.testing.assert_array_equal(pixels[..., 4], depth)  # OpenImageIO: float channel as float


@pytest.mark.parametrize("compression", ["none", "zips", "zip"])
@pytest.mark.parametrize("depth", [False, True])
def test_header_is_the_one_openimageio_writes(tmp_path: Path, compression: str, depth: bool) -> None:
    """Byte for byte: every attribute with OpenImageIO's name, EXR type and value, in its order."""
    rgba = _rgba(np.random.default_rng(8), 18, 11)
    z = np.full((18, 11), 5.0, np.float32) if depth else None
    mine, theirs = tmp_path / "mine.exr", tmp_path / "oiio.exr"
    _write(mine, rgba, z, compression=compression)
    pixels = rgba if z is None else np.concatenate([rgba.astype(np.float32), z[..., None]], axis=2)
    oiio_write_exr(theirs, np.ascontiguousarray(pixels), attributes=ATTRIBUTES, compression=compression)
    dtypes = {name: np.dtype(np.float16) for name in "RGBA"} | ({"Z": np.dtype(np.float32)} if depth else {})
    header = header_bytes(
        11, 18, channels=dtypes, compression=compression, attributes={"colorInteropID": COLOR_SPACE, **ATTRIBUTES}
    )
    assert mine.read_bytes()[: len(header)] == header
    assert theirs.read_bytes()[: len(header)] == header
    ours, reference = _oiio_read(mine)[1], _oiio_read(theirs)[1]
    as_list = lambda spec: [(p.name, str(p.type), p.value) for p in spec.extra_attribs]
    assert as_list(ours) == as_list(reference)
    assert ours.getattribute("oiio:ColorSpace") == COLOR_SPACE
    assert str(ours.getattribute("exmap:pose_rvec")) and ours.getattribute("exmap:frame") == 12


def test_long_attribute_names_set_the_version_flag(tmp_path: Path) -> None:
    name = "exmap:" + "x" * 40
    header = header_bytes(2, 2, channels={"A": np.float16}, compression="zip", attributes={name: 1})
    assert struct.unpack_from("<ii", header) == (20000630, 0x402)
    path = tmp_path / "long.exr"
    with open(path, "wb") as file:
        write_scanline_exr(file, {"A": np.ones((2, 2), np.float16)}, attributes={name: 1})
    assert _oiio_read(path)[1].getattribute(name) == 1
    assert struct.unpack_from("<ii", header_bytes(2, 2, channels={"A": np.float16}, compression="zip", attributes={})) == (
        20000630,
        2,
    )


def test_incompressible_chunks_are_stored_raw_and_read_back(tmp_path: Path) -> None:
    rng = np.random.default_rng(9)
    noise = rng.integers(0, 1 << 16, size=(33, 64, 4), dtype=np.uint16).view(np.float16)  # uniform bytes
    noise[16:32] = 0.25  # the middle chunk compresses
    data = io.BytesIO()
    write_scanline_exr(data, {n: noise[..., c] for c, n in enumerate("RGBA")}, attributes={}, compression="zip", level=1)
    header = header_bytes(64, 33, channels=dict.fromkeys("RGBA", np.float16), compression="zip", attributes={})
    sizes = _chunk_sizes(data.getvalue(), len(header), 3)
    line = 64 * 4 * 2
    assert sizes[0] == 16 * line and sizes[2] == line  # raw: deflate did not shrink them
    assert sizes[1] < line
    path = tmp_path / "noise.exr"
    path.write_bytes(data.getvalue())
    np.testing.assert_array_equal(_oiio_read(path)[0].view(np.uint16), noise.view(np.uint16))


@pytest.mark.parametrize("level", list(ZIP_LEVELS))
def test_every_level_is_lossless_and_deterministic(tmp_path: Path, level: int) -> None:
    rgba = _rgba(np.random.default_rng(10), 50, 30)
    first, second = tmp_path / "a.exr", tmp_path / "b.exr"
    _write(first, rgba, compression="zip", level=level)
    _write(second, rgba.copy(), compression="zip", level=level)
    assert first.read_bytes() == second.read_bytes()
    np.testing.assert_array_equal(_oiio_read(first)[0].view(np.uint16), rgba.view(np.uint16))


def test_zip_predictor_is_imfzips_loop() -> None:
    """Against a transcription of ImfZip.cpp's two loops (reorder, then predictor), byte by byte."""
    rng = np.random.default_rng(11)
    blocks = rng.integers(0, 256, size=(3, 38), dtype=np.uint8)
    for block, got in zip(blocks, zip_predictor(blocks)):
        raw = [int(b) for b in block]
        reordered = raw[0::2] + raw[1::2]
        expected = [reordered[0]] + [(reordered[i] - reordered[i - 1] + 128 + 256) % 256 for i in range(1, len(reordered))]
        assert list(got) == expected


def test_scanlines_are_planar_per_line_sorted_by_name() -> None:
    r = np.array([[1, 2]], np.float16)
    z = np.array([[3, 4]], np.float32)
    a = np.array([[5, 6]], np.float16)
    line = scanlines({"Z": z, "R": r, "A": a})[0].tobytes()
    assert line == a.tobytes() + r.tobytes() + z.tobytes()
    assert LINES_PER_CHUNK == {"none": 1, "zips": 1, "zip": 16}


def test_bad_arguments_are_rejected() -> None:
    ones = {"R": np.ones((2, 2), np.float16)}
    with pytest.raises(ValueError, match="compression"):
        write_scanline_exr(io.BytesIO(), ones, attributes={}, compression="piz")
    with pytest.raises(ValueError, match="level"):
        write_scanline_exr(io.BytesIO(), ones, attributes={}, level=0)
    with pytest.raises(ValueError, match="one size"):
        scanlines({"R": np.ones((2, 2), np.float16), "G": np.ones((2, 3), np.float16)})
    with pytest.raises(TypeError, match="float16 or float32"):
        scanlines({"R": np.ones((2, 2), np.float64)})
    with pytest.raises(TypeError, match="'exmap:valid'"):
        write_scanline_exr(io.BytesIO(), ones, attributes={"exmap:valid": True})
    with pytest.raises(ValueError, match="dataWindow"):
        write_scanline_exr(io.BytesIO(), ones, attributes={"dataWindow": 1})


@pytest.mark.parametrize("height", [16 * 7, 16 * 7 + 5])
def test_zero_blocks_get_the_bytes_of_compressing_them(tmp_path: Path, height: int) -> None:
    """Zero rows above and below the picture (and a zero chunk between): the shortcut for the
    outer zero chunks gives the bytes of preprocessing and deflating each chunk, and both
    OpenEXR and OpenImageIO read the halves back."""
    rgba = np.zeros((height, 24, 4), np.float16)
    rgba[20:40] = _rgba(np.random.default_rng(12), 20, 24)
    rgba[64:80] = 0.0  # a zero chunk between non-zero ones: the general path
    rgba[90:96, 3] = -0.0  # sign bits: not zero bytes
    lines = scanlines({name: rgba[..., c] for c, name in enumerate("RGBA")})
    full = height // 16 * 16
    blocks = [lines[:full].reshape(-1, 16 * lines.shape[1])] + ([lines[full:].reshape(1, -1)] if full < height else [])
    expected = []
    for rows in blocks:
        for block, predicted in zip(rows, zip_predictor(rows)):
            packed = zlib_ng.compress(predicted, ZIP_LEVEL)  # the writer's deflater
            expected.append(packed if len(packed) < len(block) else block.tobytes())
    got = chunk_data(lines, compression="zip", level=ZIP_LEVEL)
    assert [bytes(c) for c in got] == expected
    path = tmp_path / "frame.exr"
    _write(path, rgba, compression="zip")
    np.testing.assert_array_equal(_oiio_read(path)[0].view(np.uint16), rgba.view(np.uint16))
    with OpenEXR.File(str(path)) as exr:
        np.testing.assert_array_equal(exr.channels()["RGBA"].pixels.view(np.uint16), rgba.view(np.uint16))


def test_an_all_zero_frame_is_read_back() -> None:
    lines = scanlines({"R": np.zeros((33, 5), np.float16)})
    chunks = chunk_data(lines, compression="zip", level=ZIP_LEVEL)
    assert len(chunks) == 3 and chunks[0] == chunks[1] == zero_block_data(16 * 10, ZIP_LEVEL)
    assert zlib.decompress(chunks[0]) == bytes([0] + [128] * 159)
    assert chunks[2] == bytes(10)  # a 10-byte chunk does not shrink: stored raw
