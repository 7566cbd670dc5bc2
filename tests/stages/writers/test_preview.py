"""preview.side_by_side: common even height, aspect ratios kept, performer left, result right."""

from pathlib import Path

import numpy as np
import pytest

from runner.stage import StageError
from stages.writers.preview import SideBySide, side_by_side, side_by_side_size
from tests.memory_stream import MemoryStream, files_context

DEFAULTS = {param.name: param.default for param in SideBySide.params}


def test_layout_sizes() -> None:
    # performer 640x480 scaled to the result's height 800: 640 * 800 / 480 = 1066.7 -> 1066
    assert side_by_side_size((480, 640), (800, 600)) == (800, 1066, 600)
    assert side_by_side_size((480, 640), (800, 600), height=240) == (240, 320, 180)
    h, w1, w2 = side_by_side_size((333, 501), (601, 799))
    assert h % 2 == w1 % 2 == w2 % 2 == 0
    assert abs(w1 / h - 501 / 333) < 2 / h and abs(w2 / h - 799 / 601) < 2 / h


def test_content_left_performer_right_result() -> None:
    performer = np.full((48, 64, 3), (10, 200, 30), np.uint8)
    result = np.full((80, 60, 3), (0.5, 0.25, 1.0), np.float32)
    out = side_by_side(performer, result)
    assert out.dtype == np.uint8 and out.shape == (80, 106 + 60, 3)
    np.testing.assert_array_equal(out[:, :106], np.broadcast_to([10, 200, 30], (80, 106, 3)))
    np.testing.assert_array_equal(out[:, 106:], np.broadcast_to([128, 64, 255], (80, 60, 3)))


def test_stage_stream_info_and_frames(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    performer = MemoryStream(rng.integers(0, 256, (4, 45, 61, 3), dtype=np.uint8), fps=25.0)
    result = MemoryStream(rng.random((4, 63, 51, 3), dtype=np.float32), fps=25.0)
    inputs = {"performer": performer, "result": result}
    stage, params = SideBySide(), {"height": 0, "scale": 1.0}
    info = stage.stream_info(inputs, params)
    out = stage.process(1, 3, inputs, params, files_context(tmp_path))["frames"]
    assert out.shape == (2, info.height, info.width, 3) and out.dtype == np.uint8
    assert (info.frames, info.fps, info.height) == (4, 25.0, 62)
    assert info.width % 2 == 0
    np.testing.assert_array_equal(out[0], side_by_side(performer.frames[1], result.frames[1]))


def test_frame_count_mismatch_is_a_stage_error() -> None:
    performer = MemoryStream(np.zeros((3, 8, 8, 3), np.uint8))
    result = MemoryStream(np.zeros((4, 8, 8, 3), np.float32))
    with pytest.raises(StageError, match="3 frames"):
        SideBySide().stream_info({"performer": performer, "result": result}, DEFAULTS)


def test_default_is_half_the_result_height_and_height_wins_over_scale(tmp_path: Path) -> None:
    """The demo's sizes: a 640x480 performer beside a 600x800 result -> 400 px high, 534 + 300 wide."""
    performer = MemoryStream(np.full((2, 480, 640, 3), 200, np.uint8))
    result = MemoryStream(np.full((2, 800, 600, 3), 0.25, np.float16))
    inputs = {"performer": performer, "result": result}
    info = SideBySide().stream_info(inputs, DEFAULTS)
    assert (info.height, info.width) == (400, 534 + 300)
    out = SideBySide().process(0, 2, inputs, DEFAULTS, files_context(tmp_path))["frames"]
    assert out.shape == (2, 400, 834, 3)
    np.testing.assert_array_equal(out[:, :, :534], 200)
    np.testing.assert_array_equal(out[:, :, 534:], round(0.25 * 255))
    explicit = SideBySide().stream_info(inputs, {**DEFAULTS, "height": 240})
    assert (explicit.height, explicit.width) == (240, 320 + 180)


def test_negative_height_is_refused_by_the_declaration():
    """The range is declared on the parameter, so the pipeline loader refuses it (exit 2)."""
    height = next(p for p in SideBySide.params if p.name == "height")
    assert height.problem(-2) == "out of range: expected 0 <= height <= 8192, got -2"
    assert height.problem(0) is None


def test_half_size_panels_average_pixel_blocks_and_milder_shrinks_interpolate() -> None:
    """The demo's preview: the 800x600 result halved is the mean of each 2x2 block (half floats
    quantized first); the 480x640 performer to 400 rows follows a linear ramp (bilinear)."""
    rng = np.random.default_rng(3)
    result = rng.random((80, 60, 3), dtype=np.float32).astype(np.float16)
    ramp = np.broadcast_to(np.arange(64, dtype=np.uint8)[None, :, None] * 4, (48, 64, 3))
    out = side_by_side(ramp, result, height=40)
    h, w_left, w_right = side_by_side_size(ramp.shape[:2], result.shape[:2], height=40)
    quantized = np.round(np.clip(result.astype(np.float32), 0, 1) * 255)
    blocks = quantized.reshape(40, 2, 30, 2, 3).mean(axis=(1, 3))
    assert np.abs(out[:, w_left:].astype(np.float64) - blocks).max() <= 0.5
    # bilinear with OpenCV's pixel-centre mapping: x_src = (x + 0.5) * 64 / w_left - 0.5
    x = (np.arange(w_left) + 0.5) * 64 / w_left - 0.5
    expected = 4 * np.clip(x, 0, 63)
    assert np.abs(out[0, :w_left, 0] - expected).max() <= 1.0
