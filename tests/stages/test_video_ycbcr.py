"""The H.264 writer's R'G'B' -> Y'CbCr 4:2:0 conversion (stages.color.rgb_to_ycbcr420) against an
independent float implementation of BT.601 limited range and against swscale, and the writer
handing the encoder exactly those planes (x264 at crf 0 is lossless: the decoded planes are the
ones converted; heights not a multiple of 4 included)."""

from __future__ import annotations

from pathlib import Path

import av
import numpy as np
import pytest

from scripts.make_test_clip import synthetic_frames
from stages.color import rgb_to_ycbcr420
from stages.video import VideoWriter


def _bt601_limited(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact (float) Y' (H, W), Cb, Cr (H/2, W/2) of uint8 RGB (H, W, 3), chroma of each 2x2
    block's mean colour: Rec. ITU-R BT.601 with Kr = 0.299, Kb = 0.114, 8-bit studio range."""
    h, w = rgb.shape[:2]
    e = rgb.astype(np.float64) / 255

    def luma(c: np.ndarray) -> np.ndarray:
        return 0.299 * c[..., 0] + 0.587 * c[..., 1] + 0.114 * c[..., 2]

    mean = e.reshape(h // 2, 2, w // 2, 2, 3).mean(axis=(1, 3))
    return (16 + 219 * luma(e), 128 + 224 * (mean[..., 2] - luma(mean)) / 1.772, 128 + 224 * (mean[..., 0] - luma(mean)) / 1.402)


@pytest.fixture(scope="module")
def images() -> np.ndarray:
    """Smooth test pattern, uniform noise, and the corners of the RGB cube (saturated colours)."""
    rng = np.random.default_rng(7)
    cube = np.array([[r, g, b] for r in (0, 255) for g in (0, 255) for b in (0, 255)], np.uint8)
    corners = np.repeat(np.repeat(cube.reshape(2, 4, 3), 8, axis=0), 8, axis=1)  # (16, 32, 3)
    return [synthetic_frames(3, 4, width=96, height=64)[0], rng.integers(0, 256, (48, 70, 3), np.uint8), corners]


def test_planes_are_bt601_limited_range_within_rounding(images):
    for image in images:
        for plane, exact in zip(rgb_to_ycbcr420(image), _bt601_limited(image), strict=True):
            assert plane.shape == exact.shape and plane.dtype == np.uint8
            error = np.abs(plane - exact)
            assert error.max() < 0.9 and error.mean() < 0.3  # rounding (fixed point, 2x2 mean)


def test_saturated_colours_reach_the_studio_range_ends(images):
    y, cb, cr = rgb_to_ycbcr420(images[2])
    assert (y.min(), y.max()) == (16, 235) and (cb.min(), cb.max()) == (16, 240)
    assert (cr.min(), cr.max()) == (16, 240)


def test_matches_swscale_within_rounding(images):
    """swscale (what the writer used before): luma within one level; its chroma filter is not a
    2x2 box, so chroma differs a few levels at sharp edges only (PSNR over 50 dB)."""
    image = images[0]
    swscale = _planes(av.VideoFrame.from_ndarray(image, format="rgb24").reformat(format="yuv420p", threads=1))
    ours = [plane.astype(np.int64) for plane in rgb_to_ycbcr420(image)]
    assert np.abs(ours[0] - swscale[0]).max() <= 1
    chroma_mse = np.mean([np.mean((a - b) ** 2) for a, b in zip(ours[1:], swscale[1:])])
    assert 10 * np.log10(255**2 / chroma_mse) > 35


def test_gray_is_luma_only():
    gray = np.arange(0, 256, dtype=np.uint8).reshape(16, 16, 1)
    y, cb, cr = rgb_to_ycbcr420(gray)
    assert np.abs(y - (16 + 219 * gray[..., 0].astype(np.float64) / 255)).max() < 0.6
    assert (cb == 128).all() and (cr == 128).all()
    for a, b in zip(rgb_to_ycbcr420(gray[..., 0]), rgb_to_ycbcr420(np.repeat(gray, 3, axis=2)), strict=True):
        assert np.array_equal(a, b)


def test_out_planes_may_have_padded_rows(images):
    """An FFmpeg frame's planes (lines padded past the width) are filled in place."""
    image = images[1]  # 70 px wide
    frame = av.VideoFrame(70, 48, "yuv420p")
    views = tuple(np.frombuffer(p, np.uint8).reshape(p.height, p.line_size)[:, : p.width] for p in frame.planes)
    assert views[0].strides[0] > 70  # padded: the test covers strided rows
    rgb_to_ycbcr420(image, out=views)
    for a, b in zip(_planes(frame), rgb_to_ycbcr420(image), strict=True):
        assert np.array_equal(a, b)
    with pytest.raises(ValueError, match="expected out planes"):
        rgb_to_ycbcr420(image, out=views[:2] + (np.empty((24, 36), np.uint8),))


@pytest.mark.parametrize(
    "image, error",
    [
        (np.zeros((5, 4, 3), np.uint8), ValueError),
        (np.zeros((4, 4, 2), np.uint8), ValueError),
        (np.zeros((0, 4, 3), np.uint8), ValueError),
        (np.zeros((4, 4, 3), np.float32), TypeError),
    ],
)
def test_bad_images_are_refused(image, error):
    with pytest.raises(error, match="rgb_to_ycbcr420: expected"):
        rgb_to_ycbcr420(image)


def _planes(frame: av.VideoFrame) -> list[np.ndarray]:
    """A yuv420p frame's Y', Cb, Cr planes (PyAV's own copy, ``to_ndarray``)."""
    i420 = frame.to_ndarray()
    h, w = frame.height, frame.width
    return [
        i420[:h],
        i420[h:].reshape(-1)[: h * w // 4].reshape(h // 2, w // 2),
        i420[h:].reshape(-1)[h * w // 4 :].reshape(h // 2, w // 2),
    ]


def _decoded_planes(path: Path) -> list[list[np.ndarray]]:
    with av.open(str(path)) as container:
        return [_planes(frame) for frame in container.decode(video=0)]


@pytest.mark.parametrize("width, height, channels", [(96, 64, 3), (63, 47, 3), (40, 30, 3), (40, 30, 1)])
def test_writer_encodes_exactly_the_converted_planes(tmp_path, width, height, channels):
    """crf 0 (x264 lossless, qp 0): the decoded planes are rgb_to_ycbcr420 of the frames written (odd
    sizes padded by repeating the last row / column; gray frames), so the writer converts them
    with it and nothing else; and the same frames give the same bytes."""
    frames = synthetic_frames(0, 6, width=width, height=height)
    if channels == 1:
        frames = frames[..., :1]
    paths = [tmp_path / f"{k}.mp4" for k in "ab"]
    for path in paths:
        with VideoWriter(path, fps=25, width=width, height=height, crf=0, preset="ultrafast") as writer:
            writer.write(frames)
    assert paths[0].read_bytes() == paths[1].read_bytes()
    padded = np.pad(frames, ((0, 0), (0, height % 2), (0, width % 2), (0, 0)), mode="edge")
    decoded = _decoded_planes(paths[0])
    assert len(decoded) == len(frames)
    for plane, image in zip(decoded, padded):
        for a, b in zip(plane, rgb_to_ycbcr420(image), strict=True):
            assert np.array_equal(a, b)
