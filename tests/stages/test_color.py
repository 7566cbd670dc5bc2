"""sRGB <-> linear (IEC 61966-2-1): known values, round trips, numpy/torch agreement, OCIO check."""

import numpy as np
import OpenImageIO as oiio
import pytest
import torch

from stages.color import linear_to_srgb, luma_float32, luma_opencv, srgb_to_linear, to_uint8, to_unit_float

# (sRGB-encoded, linear) pairs from the standard's piecewise definition.
KNOWN = [
    (0.0, 0.0),
    (0.04045, 0.0031308049535603713),  # 0.04045 / 12.92, the break point
    (0.5, 0.21404114048223255),  # ((0.5 + 0.055) / 1.055) ** 2.4
    (1.0, 1.0),
]


@pytest.mark.parametrize(("encoded", "linear"), KNOWN)
def test_known_values_numpy(encoded: float, linear: float) -> None:
    assert srgb_to_linear(np.float64(encoded)) == pytest.approx(linear, abs=1e-15)
    # the standard's two thresholds (0.04045, 0.0031308) disagree by ~3e-8 at the break point
    assert linear_to_srgb(np.float64(linear)) == pytest.approx(encoded, abs=5e-8)


def test_known_values_torch_match_numpy() -> None:
    encoded = torch.tensor([e for e, _ in KNOWN], dtype=torch.float64)
    linear = srgb_to_linear(encoded)
    assert isinstance(linear, torch.Tensor) and linear.dtype == torch.float64
    np.testing.assert_allclose(linear.numpy(), [lin for _, lin in KNOWN], atol=1e-15)


def test_round_trip_beyond_unit_range() -> None:
    x = np.linspace(-0.3, 1.7, 2001)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-12)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-12)
    assert np.all(np.diff(srgb_to_linear(x)) > 0)  # monotone, no NaN from the unused branch


def test_float32_keeps_dtype_and_round_trips() -> None:
    x = np.random.default_rng(0).random((4, 5, 3), dtype=np.float32)
    lin = srgb_to_linear(x)
    assert lin.dtype == np.float32 and lin.shape == x.shape
    np.testing.assert_allclose(linear_to_srgb(lin), x, atol=1e-6)
    t = torch.from_numpy(x)
    np.testing.assert_allclose(srgb_to_linear(t).numpy(), lin, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(t)).numpy(), x, atol=1e-6)


def test_matches_opencolorio_srgb() -> None:
    """OpenImageIO's OCIO built-in config as an independent implementation (it approximates pow)."""
    x = np.linspace(0.0, 1.0, 256, dtype=np.float32).reshape(16, 16, 1).repeat(3, axis=2)
    buf = oiio.ImageBufAlgo.colorconvert(oiio.ImageBuf(x), "srgb_rec709_scene", "lin_rec709_scene")
    np.testing.assert_allclose(srgb_to_linear(x), buf.get_pixels(oiio.FLOAT), atol=1e-4)


def test_segments_meet_at_break_point() -> None:
    below = 0.04045 / 12.92
    above = ((0.04045 + 0.055) / 1.055) ** 2.4
    assert srgb_to_linear(np.float64(0.04045 + 1e-12)) == pytest.approx(above)
    assert abs(below - above) < 1e-7


def test_quantization() -> None:
    x = np.array([-0.5, 0.0, 0.5, 1.0, 2.0, 254.6 / 255])
    np.testing.assert_array_equal(to_uint8(x), [0, 0, 128, 255, 255, 255])
    assert to_uint8(torch.tensor(x)).dtype == torch.uint8
    u = np.array([0, 51, 255], np.uint8)
    assert to_uint8(u) is u
    np.testing.assert_allclose(to_unit_float(u), [0.0, 0.2, 1.0], rtol=1e-7)
    assert to_unit_float(torch.from_numpy(u)).dtype == torch.float32


def test_half_floats_quantize_as_float32() -> None:
    """float16 arrays take OpenCV's path: every half bit pattern (0, 1, the 0.5/255 rounding
    boundaries, above 1, below 0, subnormals, +-inf, NaN) gives the float32 formula's uint8,
    in any shape and memory layout."""
    every = np.arange(1 << 16, dtype=np.uint16).view(np.float16)
    with np.errstate(invalid="ignore"):
        expected = np.round(np.clip(every.astype(np.float32), 0, 1) * 255).astype(np.uint8)
    assert expected[every == np.inf] == 255 and expected[np.isnan(every)].max() == 0
    for shape in [(65536,), (256, 256), (16, 64, 64), (4, 64, 64, 4)]:
        got = to_uint8(every.reshape(shape))
        assert got.shape == shape and got.dtype == np.uint8
        np.testing.assert_array_equal(got.reshape(-1), expected)
    strided = every.reshape(256, 256)[1::3, ::2]
    np.testing.assert_array_equal(to_uint8(strided), expected.reshape(256, 256)[1::3, ::2])
    assert to_uint8(np.zeros((0, 3), np.float16)).shape == (0, 3)


def test_luma_opencv_is_bt601_in_15_bit_fixed_point():
    """uint8: ``(9798 R + 19235 G + 3735 B + 2^14) >> 15`` (weights summing to 2^15), written out
    here; float32: the weights, within float32 rounding. Any leading shape."""
    rgb = np.random.default_rng(3).integers(0, 256, (2, 64, 96, 3), dtype=np.uint8)
    wide = rgb.astype(np.int64)
    expected = (9798 * wide[..., 0] + 19235 * wide[..., 1] + 3735 * wide[..., 2] + (1 << 14)) >> 15
    gray = luma_opencv(rgb)
    assert gray.shape == (2, 64, 96) and gray.dtype == np.uint8
    np.testing.assert_array_equal(gray, expected)
    unit = rgb.astype(np.float32) / 255.0
    np.testing.assert_allclose(luma_opencv(unit), unit.astype(np.float64) @ [0.299, 0.587, 0.114], rtol=0, atol=1e-6)
    assert luma_opencv(unit).dtype == np.float32
    with pytest.raises(ValueError, match="RGB images"):
        luma_opencv(np.zeros((4, 4), np.uint8))


def test_luma_float32_is_not_rounded():
    rgb = np.array([[10, 20, 30], [255, 255, 255], [1, 0, 0]], np.uint8)
    luma = luma_float32(rgb)
    assert luma.dtype == np.float32
    np.testing.assert_allclose(luma, [0.299 * 10 + 0.587 * 20 + 0.114 * 30, 255.0, 0.299], rtol=1e-6)
    assert luma_opencv(rgb[None])[0, 2] == 0  # where the uint8 path rounds 0.299 down
