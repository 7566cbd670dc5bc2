"""Half-float lookup tables give the function's own values, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from stages.color import to_uint8
from stages.writers.exr import srgb_decode
from stages.writers.lut import apply_elementwise, half_table


@pytest.mark.parametrize("fn", [to_uint8, srgb_decode])
def test_lookup_equals_calling_the_function_on_every_half_float(fn):
    every = np.arange(1 << 16, dtype=np.uint16).view(np.float16).reshape(256, 128, 2)
    finite = every[np.isfinite(every)]
    direct = fn(finite)
    looked_up = apply_elementwise(fn, finite)
    assert looked_up.dtype == direct.dtype and looked_up.shape == direct.shape
    assert looked_up.tobytes() == direct.tobytes()


def test_lookup_keeps_the_shape_and_reads_non_contiguous_frames():
    rng = np.random.default_rng(0)
    frames = rng.uniform(-0.1, 1.1, (2, 5, 7, 3)).astype(np.float16)[:, ::2]
    np.testing.assert_array_equal(apply_elementwise(to_uint8, frames), to_uint8(frames))
    assert apply_elementwise(to_uint8, frames).shape == (2, 3, 7, 3)


def test_other_dtypes_call_the_function():
    calls = []

    def double(x):
        calls.append(x.dtype)
        return 2 * x

    np.testing.assert_array_equal(apply_elementwise(double, np.array([1.0, 2.0])), [2.0, 4.0])
    assert calls == [np.float64]


def test_a_function_that_is_not_elementwise_is_refused():
    def total(x):
        return np.sum(x.astype(np.float32))

    with pytest.raises(ValueError, match="elementwise"):
        half_table(total)
