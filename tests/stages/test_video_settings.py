"""write.video's encoder settings: the preset and thread count reach x264 (its own record of its
options in the stream), every preset gives a picture of the same quality, the colour tags say what
the conversion did (checked against the BT.601 limited-range formula), and bad values are refused."""

from __future__ import annotations

import re
from pathlib import Path

import av
import numpy as np
import pytest

from runner.stage import StageError
from scripts.make_test_clip import synthetic_frames
from stages.color import luma_opencv
from stages.video import X264_PRESETS, VideoWriter, WriteVideo


def _encode(path: Path, frames: np.ndarray, **options) -> bytes:
    options = {"crf": 12, **options}
    with VideoWriter(path, fps=25, width=frames.shape[2], height=frames.shape[1], **options) as writer:
        writer.write(frames)
    return path.read_bytes()


def _x264_options(data: bytes) -> dict[str, str]:
    """x264's options as it records them in its SEI message ('... options: cabac=1 ref=3 ...')."""
    text = re.search(rb"options: ([ -~]+)", data).group(1).decode()
    return dict(item.split("=", 1) for item in text.split() if "=" in item)


def _decode(path: Path) -> np.ndarray:
    with av.open(str(path)) as container:
        return np.stack([f.to_ndarray(format="rgb24") for f in container.decode(video=0)])


@pytest.fixture(scope="module")
def frames() -> np.ndarray:
    return synthetic_frames(0, 12, width=96, height=64)


@pytest.mark.parametrize("preset, subme", [("ultrafast", "0"), ("veryfast", "2"), ("medium", "7")])
def test_preset_reaches_x264_and_keeps_the_picture(tmp_path, frames, preset, subme):
    """x264's presets set its sub-pixel motion refinement (subme 0, 2, 7): the option reached
    the encoder. The quality is crf's, not the preset's: luma PSNR over 38 dB for each."""
    options = _x264_options(_encode(tmp_path / "v.mp4", frames, preset=preset))
    assert options["subme"] == subme and options["mbtree"] == "0"
    decoded = _decode(tmp_path / "v.mp4")
    mse = np.mean((luma_opencv(decoded).astype(np.float64) - luma_opencv(frames)) ** 2)
    assert 10 * np.log10(255.0**2 / mse) > 38


def test_thread_count_is_the_slice_count_and_output_repeats(tmp_path):
    """x264 slice threads: the stream depends on the count, never on the run (frames of 10
    macroblock rows: x264 does not cut frames of few rows into slices)."""
    frames = synthetic_frames(0, 12, width=224, height=160)
    one = _encode(tmp_path / "a.mp4", frames, threads=1)
    two = [_encode(tmp_path / f"{k}.mp4", frames, threads=2) for k in "bc"]
    assert two[0] == two[1] != one
    options = _x264_options(two[0])
    assert (options["threads"], options["sliced_threads"], options["slices"]) == ("2", "1", "2")
    assert _x264_options(one)["threads"] == "1"


def test_colour_tags_match_the_conversion(tmp_path):
    """Flat colours: the decoded Y', Cb, Cr planes are BT.601 limited range of the RGB written
    (Y' = 16 + 219 (0.299 R + 0.587 G + 0.114 B) / 255, Cb/Cr = 128 + 224 (B or R - Y) / (255 k)),
    and the stream is tagged so: matrix BT.470BG/601, TV range, BT.709 primaries, sRGB transfer."""
    colours = np.array([[200, 40, 30], [20, 180, 60], [30, 60, 220], [128, 128, 128]], np.float64)
    frames = np.stack([np.broadcast_to(c, (64, 64, 3)).astype(np.uint8) for c in colours])
    _encode(tmp_path / "flat.mp4", frames, crf=0)
    with av.open(str(tmp_path / "flat.mp4")) as container:
        context = container.streams.video[0].codec_context
        tags = (context.colorspace, context.color_range, context.color_primaries, context.color_trc)
        planes = [f.to_ndarray() for f in container.decode(video=0)]  # yuv420p: Y rows then U, V
    assert tags == (5, 1, 1, 13)
    r, g, b = colours.T
    y = 0.299 * r + 0.587 * g + 0.114 * b
    expected = np.stack([16 + 219 * y / 255, 128 + 224 * (b - y) / (255 * 1.772), 128 + 224 * (r - y) / (255 * 1.402)], axis=1)
    for plane, (ey, eu, ev) in zip(planes, expected):
        assert abs(plane[:64].mean() - ey) < 1.5
        assert abs(plane[64:80].mean() - eu) < 1.5 and abs(plane[80:96].mean() - ev) < 1.5


def test_bad_preset_and_threads_are_refused(tmp_path):
    with pytest.raises(StageError, match="unknown x264 preset 'quick'"):
        VideoWriter(tmp_path / "x.mp4", fps=25, width=8, height=8, preset="quick")
    with pytest.raises(StageError, match="threads must be >= 1, got 0"):
        VideoWriter(tmp_path / "x.mp4", fps=25, width=8, height=8, threads=0)


def test_stage_declares_preset_and_threads():
    """The loader checks declared choices and ranges (a bad --set is refused before the run)."""
    params = {p.name: p for p in WriteVideo.params}
    assert params["preset"].default == "superfast" and params["preset"].choices == X264_PRESETS
    assert params["preset"].problem("quick") is not None
    assert params["threads"].default == 2 and params["threads"].in_key  # the bytes depend on it
    assert params["threads"].problem(0) is not None and params["threads"].problem(2) is None
