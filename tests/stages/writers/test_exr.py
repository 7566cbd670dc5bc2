"""write.exr: round trip through OpenImageIO, metadata, atomic writes, clear errors."""

import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

from runner.stage import StageError
from stages.color import srgb_to_linear, to_unit_float
from stages.writers.atomic import atomic_write, temp_name
from stages.writers import exr_file
from stages.writers.exr import (
    COMPRESSIONS,
    DEPTH_UNIT,
    WriteExr,
    coverage_box,
    exr_name,
    oiio_write_exr,
    to_linear_rgba,
    write_exr,
)
from stages.writers.exr_file import ZIP_LEVEL
from tests.memory_stream import MemoryStream, files_context

REPO = Path(__file__).resolve().parents[3]
HALF_RTOL = 2.0**-11  # half float: 11 significant bits
HALF_ATOL = 2.0**-24  # smallest half subnormal
FPS = 30.0
T, H, W = 3, 10, 14


def _inputs(rng: np.random.Generator, *, mask: bool = True) -> dict:
    inputs = {
        "frames": MemoryStream(rng.random((T, H, W, 3), dtype=np.float32), fps=FPS),
        "pose": {
            "rvec": rng.normal(size=(T, 3)),
            "tvec": rng.normal(size=(T, 3)) * 500,
            "R": np.tile(np.eye(3), (T, 1, 1)),
            "reproj_err_px": rng.random(T),
            "valid": np.array([True, False, True]),
        },
        "similarity": {
            "params": rng.normal(size=(T, 4)),
            "residual_px": rng.random(T),
            "valid": np.array([True, True, False]),
        },
    }
    if mask:
        inputs["mask"] = MemoryStream(rng.random((T, H, W, 1), dtype=np.float32), fps=FPS)
    return inputs


def _read(path: Path) -> tuple[np.ndarray, oiio.ImageSpec]:
    inp = oiio.ImageInput.open(str(path))
    assert inp is not None, oiio.geterror()
    pixels = inp.read_image(oiio.FLOAT)
    spec = inp.spec()
    inp.close()
    return pixels, spec


def _params(**overrides) -> dict:
    return {"compression": "zip", "zip_level": ZIP_LEVEL, "threads": 2, **overrides}


def test_round_trip_pixels_alpha_metadata(tmp_path: Path) -> None:
    inputs = _inputs(np.random.default_rng(1))
    WriteExr().process(0, T, inputs, _params(), files_context(tmp_path))
    assert sorted(p.name for p in (tmp_path / "exr").iterdir()) == [exr_name(i) for i in range(T)]
    for i in range(T):
        pixels, spec = _read(tmp_path / "exr" / f"frame.{i:06d}.exr")
        assert spec.format == oiio.TypeDesc("half")
        assert spec.channelnames == ("R", "G", "B", "A") and spec.alpha_channel == 3
        alpha = inputs["mask"].frames[i]
        expected = srgb_to_linear(inputs["frames"].frames[i].astype(np.float64)) * alpha  # associated alpha
        np.testing.assert_allclose(pixels[..., :3], expected, rtol=HALF_RTOL, atol=HALF_ATOL)
        np.testing.assert_allclose(pixels[..., 3:], alpha, rtol=HALF_RTOL, atol=HALF_ATOL)
        assert spec.getattribute("compression") == "zip"
        assert spec.getattribute("exmap:frame") == i
        assert spec.getattribute("exmap:time_s") == pytest.approx(i / FPS, rel=1e-7)
        assert spec.getattribute("exmap:fps") == FPS
        np.testing.assert_allclose(spec.getattribute("exmap:pose_rvec"), inputs["pose"]["rvec"][i], rtol=1e-6)
        np.testing.assert_allclose(spec.getattribute("exmap:pose_tvec"), inputs["pose"]["tvec"][i], rtol=1e-6)
        assert spec.getattribute("exmap:pose_valid") == int(inputs["pose"]["valid"][i])
        np.testing.assert_allclose(spec.getattribute("exmap:similarity"), inputs["similarity"]["params"][i], rtol=1e-6)
        assert spec.getattribute("exmap:similarity_valid") == int(inputs["similarity"]["valid"][i])


def test_without_mask_is_opaque_and_chunk_uses_clip_frame_index(tmp_path: Path) -> None:
    inputs = _inputs(np.random.default_rng(2), mask=False)
    del inputs["pose"], inputs["similarity"]
    WriteExr().process(1, 3, inputs, _params(compression="piz"), files_context(tmp_path))
    assert sorted(p.name for p in (tmp_path / "exr").iterdir()) == ["frame.000001.exr", "frame.000002.exr"]
    pixels, spec = _read(tmp_path / "exr" / "frame.000002.exr")
    np.testing.assert_array_equal(pixels[..., 3], 1.0)
    expected = srgb_to_linear(inputs["frames"].frames[2].astype(np.float64))
    np.testing.assert_allclose(pixels[..., :3], expected, rtol=HALF_RTOL, atol=HALF_ATOL)
    assert spec.getattribute("compression") == "piz"
    assert spec.getattribute("exmap:frame") == 2
    assert spec.getattribute("exmap:pose_rvec") is None


def test_thread_count_does_not_change_bytes(tmp_path: Path) -> None:
    inputs = _inputs(np.random.default_rng(3))
    WriteExr().process(0, T, inputs, _params(threads=1), files_context(tmp_path / "one"))
    WriteExr().process(0, T, inputs, _params(threads=3), files_context(tmp_path / "three"))
    for i in range(T):
        name = exr_name(i)
        assert (tmp_path / "one/exr" / name).read_bytes() == (tmp_path / "three/exr" / name).read_bytes()


def test_uint8_frames_are_decoded_like_floats() -> None:
    u = np.array([[[0, 128, 255]]], np.uint8)
    np.testing.assert_allclose(to_linear_rgba(u), to_linear_rgba(u.astype(np.float32) / 255), rtol=1e-7)


def test_temp_name_never_matches_final_name(tmp_path: Path) -> None:
    final = tmp_path / "frame.000007.exr"
    names = {temp_name(final).name for _ in range(20)}
    assert len(names) == 20
    for name in names:
        assert name != final.name and not Path(name).match("frame.*.exr") and name.endswith(".part")


def test_failed_write_leaves_no_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    final = tmp_path / "frame.000000.exr"
    with pytest.raises(RuntimeError), atomic_write(final) as tmp:
        tmp.write_bytes(b"partial")
        raise RuntimeError("crash in the middle of a frame")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match=r"\(H, W, 4\)"):
        write_exr(final, np.zeros((4, 4, 3), np.float32), attributes={})

    # a write that fails half way (the disk fills after the header): clear error, no file
    def disk_full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(exr_file, "chunk_data", disk_full)
    with pytest.raises(StageError, match="frame.000000.exr.*No space"):
        write_exr(final, np.zeros((4, 4, 4), np.float32), attributes={})
    assert list(tmp_path.iterdir()) == []
    # a file OpenImageIO cannot open (piz, in a missing folder): clear error, no file
    with pytest.raises(StageError, match="missing/frame.000000.exr"):
        write_exr(tmp_path / "missing" / final.name, np.zeros((4, 4, 4), np.float16), attributes={}, compression="piz")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("compression", ["zip", "none"])
def test_own_writer_matches_openimageio_with_float_input_and_depth(tmp_path: Path, compression: str) -> None:
    """What render3d writes (float32 RGBA, float Z, its own float[9] attribute): the same half
    floats (float32 rounded to half as OpenEXR rounds), Z and attributes as OpenImageIO's file."""
    rng = np.random.default_rng(7)
    rgba = rng.normal(0, 2, (19, 13, 4)).astype(np.float32)
    rgba[0, :4, 0] = [65520.0, -1e6, 2.0**-25, 3 * 2.0**-26]  # overflow and subnormal rounding
    depth = rng.random((19, 13), dtype=np.float32) * 900
    depth[2] = np.inf
    attributes = {"exmap:frame": 4, "exmap:head_R": tuple(np.eye(3).ravel() * 0.5)}
    write_exr(tmp_path / "own.exr", rgba, attributes=attributes, compression=compression, depth=depth)
    oiio_write_exr(
        tmp_path / "oiio.exr",
        np.concatenate([rgba, depth[..., None]], axis=2),
        attributes={**attributes, "exmap:depth_unit": DEPTH_UNIT},
        compression=compression,
    )
    ours, theirs = (oiio.ImageInput.open(str(tmp_path / name)) for name in ("own.exr", "oiio.exr"))
    np.testing.assert_array_equal(
        ours.read_image(oiio.HALF)[..., :4].view(np.uint16), theirs.read_image(oiio.HALF)[..., :4].view(np.uint16)
    )
    np.testing.assert_array_equal(ours.read_image(oiio.FLOAT)[..., 4], depth)
    as_list = lambda spec: [(p.name, str(p.type), p.value) for p in spec.extra_attribs]
    assert as_list(ours.spec()) == as_list(theirs.spec())
    assert ours.spec().getattribute("exmap:depth_unit") == DEPTH_UNIT
    ours.close(), theirs.close()


KILLED_WRITER = """
import sys, numpy as np
from pathlib import Path
from stages.writers.exr import write_exr, exr_name
out = Path(sys.argv[1])
for i in range(100000):
    rgba = np.full((256, 256, 4), (i % 50) / 64, np.float32)
    write_exr(out / exr_name(i % 50), rgba, attributes={"exmap:frame": i % 50})
"""


@pytest.mark.subprocess
def test_killed_writer_leaves_only_complete_frames(tmp_path: Path) -> None:
    proc = subprocess.Popen([sys.executable, "-c", KILLED_WRITER, str(tmp_path)], cwd=REPO)
    try:
        deadline = time.monotonic() + 30
        while len(list(tmp_path.glob("frame.*.exr"))) < 3 and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(0.05)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    finals = sorted(tmp_path.glob("frame.*.exr"))
    assert finals, "the writer produced no frame before being killed"
    for path in finals:
        pixels, spec = _read(path)
        index = spec.getattribute("exmap:frame")
        assert path.name == exr_name(index)
        np.testing.assert_array_equal(pixels, index / 64)
    leftovers = {p.name for p in tmp_path.iterdir()} - {p.name for p in finals}
    assert all(name.startswith(".frame.") and name.endswith(".part") for name in leftovers)


def test_unwritable_destination_is_a_stage_error(tmp_path: Path) -> None:
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("a file where the output folder should be")
    inputs = _inputs(np.random.default_rng(4))
    ctx = files_context(blocker)
    with pytest.raises(StageError, match="not_a_folder"):
        WriteExr().process(0, T, inputs, _params(), ctx)
    # a folder standing where a frame file must go (os.replace cannot overwrite it)
    (tmp_path / "exr" / exr_name(1)).mkdir(parents=True)
    with pytest.raises(StageError, match=exr_name(1)):
        WriteExr().process(0, T, inputs, _params(), files_context(tmp_path))
    assert not [p for p in (tmp_path / "exr").iterdir() if p.name.endswith(".part")]


def test_mismatched_inputs_are_stage_errors(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    inputs = _inputs(rng)
    inputs["mask"] = MemoryStream(rng.random((T, H + 2, W, 1), dtype=np.float32), fps=FPS)
    with pytest.raises(StageError, match="'mask'"):
        WriteExr().process(0, T, inputs, _params(), files_context(tmp_path))
    inputs = _inputs(rng)
    inputs["pose"] = {k: v[:2] for k, v in inputs["pose"].items()}
    with pytest.raises(StageError, match="'pose'"):
        WriteExr().process(0, T, inputs, _params(), files_context(tmp_path))


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_every_compression_is_lossless_on_half_frames(tmp_path: Path, compression: str) -> None:
    """The synthesized frames are half floats: each codec gives back exactly the half values of
    the premultiplied linear RGBA (float32 rounded once to half), with the metadata."""
    rng = np.random.default_rng(5)
    frames = rng.random((1, 64, 48, 3), dtype=np.float32).astype(np.float16)
    mask = np.clip(rng.normal(0.5, 0.5, (1, 64, 48, 1)), 0, 1).astype(np.float16)
    inputs = {"frames": MemoryStream(frames, fps=FPS), "mask": MemoryStream(mask, fps=FPS)}
    WriteExr().process(0, 1, inputs, _params(compression=compression), files_context(tmp_path))
    inp = oiio.ImageInput.open(str(tmp_path / "exr" / exr_name(0)))
    stored, spec = inp.read_image(oiio.HALF), inp.spec()
    inp.close()
    expected = to_linear_rgba(frames[0], mask[0]).astype(np.float16)
    np.testing.assert_array_equal(stored.view(np.uint16), expected.view(np.uint16))
    assert spec.getattribute("compression") == compression
    assert (spec.getattribute("exmap:frame"), spec.getattribute("exmap:fps")) == (0, FPS)


def test_half_rgba_is_numpys_rounding_of_the_float32_products() -> None:
    """Every half bit pattern (inf and NaN included) as sRGB, under random alpha: the half RGBA
    equals numpy's round-to-nearest-even of the float32 ``srgb_to_linear(x) * alpha``, bit for bit."""
    rng = np.random.default_rng(6)
    patterns = np.arange(1 << 16, dtype=np.uint16).view(np.float16)
    srgb = rng.permutation(np.tile(patterns, 3)).reshape(256, 256, 3)
    alpha = rng.random((256, 256, 1), dtype=np.float32)
    alpha[:8] = 0.0
    with np.errstate(all="ignore"):
        expected = (srgb_to_linear(srgb.astype(np.float32)) * alpha).astype(np.float16)
        rgba = to_linear_rgba(srgb, alpha)
    assert rgba.dtype == np.float16
    np.testing.assert_array_equal(rgba[..., :3].view(np.uint16), expected.view(np.uint16))
    np.testing.assert_array_equal(rgba[..., 3:].view(np.uint16), alpha.astype(np.float16).view(np.uint16))


def test_zip_level_changes_the_bytes_not_the_pixels(tmp_path: Path) -> None:
    """Why ``zip_level`` is in the cache key: other bytes, the same half floats."""
    rng = np.random.default_rng(8)
    frames = np.repeat(np.linspace(0, 1, 64 * 48, dtype=np.float32).reshape(1, 64, 48, 1), 3, axis=3)
    inputs = {"frames": MemoryStream((frames + rng.random(frames.shape, dtype=np.float32) / 64).astype(np.float16), fps=FPS)}
    WriteExr().process(0, 1, inputs, _params(zip_level=1), files_context(tmp_path / "fast"))
    WriteExr().process(0, 1, inputs, _params(zip_level=9), files_context(tmp_path / "small"))
    fast, small = (tmp_path / name / "exr" / exr_name(0) for name in ("fast", "small"))
    assert fast.read_bytes() != small.read_bytes()
    for path in (fast, small):
        inp = oiio.ImageInput.open(str(path))
        stored = inp.read_image(oiio.HALF)
        inp.close()
        np.testing.assert_array_equal(stored.view(np.uint16), to_linear_rgba(inputs["frames"].frames[0]).view(np.uint16))


def _whole_frame_rgba(srgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """The premultiply over every pixel, in numpy: float32 products rounded once to half."""
    with np.errstate(all="ignore"):
        linear = srgb_to_linear(to_unit_float(srgb).astype(np.float32))
        a = alpha.astype(np.float32).reshape(linear.shape[:2] + (1,))
        return np.concatenate([linear * a, a], axis=2).astype(np.float16)


def _face_mask(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A soft random blob inside the frame, zero around it."""
    y, x = np.mgrid[0:height, 0:width]
    r = np.hypot((x - width * rng.uniform(0.3, 0.7)) / (0.25 * width), (y - height * rng.uniform(0.3, 0.7)) / (0.3 * height))
    return np.clip((1.05 - r) * 4, 0, 1).astype(np.float16)[..., None]


@pytest.mark.parametrize("case", ["blob", "empty", "full", "negative_zero", "corner_pixel", "float32_alpha", "uint8"])
def test_premultiply_in_the_coverage_box_equals_the_whole_frame(case: str) -> None:
    """Computed inside the box of non-zero alpha only: the same halves, bit for bit, as the
    product over every pixel."""
    rng = np.random.default_rng(13)
    srgb = rng.random((48, 40, 3), dtype=np.float32).astype(np.float16)
    alpha = _face_mask(rng, 48, 40)
    if case == "empty":
        alpha[:] = 0
    elif case == "full":
        alpha[:] = rng.random(alpha.shape).astype(np.float16)
    elif case == "negative_zero":
        alpha[:3] = -0.0  # -0 alpha: the products' sign bit is set, so these rows are computed
    elif case == "corner_pixel":
        alpha[:] = 0
        alpha[47, 39] = 0.5
    elif case == "float32_alpha":
        alpha = alpha.astype(np.float32) * np.float32(0.3)
    elif case == "uint8":
        srgb = rng.integers(0, 256, srgb.shape, dtype=np.uint8)
    got = to_linear_rgba(srgb, alpha)
    assert got.shape == (48, 40, 4) and got.dtype == np.float16
    np.testing.assert_array_equal(got.view(np.uint16), _whole_frame_rgba(srgb, alpha).view(np.uint16))


@pytest.mark.parametrize("value", [-0.0, -0.25, np.inf, -np.inf, np.nan])
def test_colour_that_does_not_vanish_under_zero_alpha_keeps_the_whole_frame(value: float) -> None:
    """-0, negative, infinite or NaN colour outside the face: its product with alpha 0 is -0 or
    NaN, not +0, so the box is the whole frame and the halves are still the products."""
    rng = np.random.default_rng(14)
    srgb = rng.random((32, 24, 3), dtype=np.float32).astype(np.float16)
    alpha = _face_mask(rng, 32, 24)
    srgb[0, 0, 1] = value
    assert coverage_box(srgb, alpha[..., 0]) == (slice(0, 32), slice(0, 24))
    np.testing.assert_array_equal(to_linear_rgba(srgb, alpha).view(np.uint16), _whole_frame_rgba(srgb, alpha).view(np.uint16))


def test_coverage_box_is_the_bounding_box_of_non_zero_alpha() -> None:
    alpha = np.zeros((10, 12), np.float16)
    alpha[2, 5] = 0.1
    alpha[6, 3] = 1.0
    srgb = np.full((10, 12, 3), 0.5, np.float16)
    assert coverage_box(srgb, alpha) == (slice(2, 7), slice(3, 6))
    assert coverage_box(srgb, np.zeros((10, 12), np.float32)) == (slice(0, 0), slice(0, 0))


def test_openimageio_writer_takes_the_planar_rgba(tmp_path: Path) -> None:
    """to_linear_rgba's view of planar memory, handed to OpenImageIO (the ``piz``/``rle`` path
    and the benchmark's reference writer), is written and read back as the same halves."""
    rng = np.random.default_rng(15)
    rgba = to_linear_rgba(rng.random((20, 16, 3), dtype=np.float32).astype(np.float16), _face_mask(rng, 20, 16))
    assert not rgba.flags["C_CONTIGUOUS"]
    oiio_write_exr(tmp_path / "planar.exr", rgba, attributes={}, compression="zip")
    inp = oiio.ImageInput.open(str(tmp_path / "planar.exr"))
    stored = inp.read_image(oiio.HALF)
    inp.close()
    np.testing.assert_array_equal(stored.view(np.uint16), rgba.view(np.uint16))


@pytest.mark.parametrize("compression", ["zip", "piz"])
def test_shot_channels_hold_the_head_the_plate_and_the_mattes(tmp_path: Path, compression: str) -> None:
    """With 'head_matte': R, G, B, A the head (associated alpha), plate.R/G/B the whole frame, face.A and
    filled.A the mattes, as OpenImageIO reads them back; the head motion in the header."""
    rng = np.random.default_rng(5)
    frames = rng.random((T, H, W, 3), dtype=np.float32)
    mattes = {port: rng.random((T, H, W, 1), dtype=np.float32).astype(np.float16) for port in ("mask", "head_matte", "filled")}
    R = np.stack([np.eye(3)] * T)
    inputs = {
        "frames": MemoryStream(frames.astype(np.float16), fps=FPS),
        **{port: MemoryStream(m, fps=FPS) for port, m in mattes.items()},
        "head": {"R": R, "t": rng.normal(size=(T, 3))},
    }
    WriteExr().process(0, T, inputs, _params(compression=compression), files_context(tmp_path))
    image = oiio.ImageInput.open(str(tmp_path / "exr" / exr_name(1)))
    spec = image.spec()
    names = spec.channelnames
    pixels = image.read_image("float")
    image.close()
    assert set(names) == {"R", "G", "B", "A", "plate.R", "plate.G", "plate.B", "face.A", "filled.A"}
    assert names[:4] == ("R", "G", "B", "A") and spec.alpha_channel == 3
    get = {n: pixels[..., names.index(n)] for n in names}
    plate = np.stack([get[f"plate.{c}"] for c in "RGB"], -1)
    linear = srgb_to_linear(frames[1].astype(np.float16).astype(np.float32))
    np.testing.assert_allclose(plate, linear, rtol=HALF_RTOL, atol=HALF_ATOL)
    head = mattes["head_matte"][1, ..., 0].astype(np.float32)
    np.testing.assert_array_equal(get["A"], head)
    np.testing.assert_allclose(np.stack([get[c] for c in "RGB"], -1), linear * head[..., None], rtol=HALF_RTOL, atol=HALF_ATOL)
    np.testing.assert_array_equal(get["face.A"], mattes["mask"][1, ..., 0].astype(np.float32))
    np.testing.assert_array_equal(get["filled.A"], mattes["filled"][1, ..., 0].astype(np.float32))
    np.testing.assert_allclose(spec.getattribute("exmap:head_t_mm"), inputs["head"]["t"][1], rtol=1e-6)
