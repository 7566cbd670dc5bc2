"""The editor engine's 8-bit conversion: rounding to nearest, clamping, OpenCV's channel order."""

from __future__ import annotations

import numpy as np
import torch

from editor.engine import to_uint8


def test_to_uint8_rounds_clamps_and_orders_bgr():
    values = torch.tensor([0.0, 0.49 / 255, 0.5 / 255, 127.5 / 255, 1.0, 1.2, -0.3], dtype=torch.float32)
    expected = np.array([0, 0, 1, 128, 255, 255, 0], np.uint8)
    rgb = torch.stack([values, values.flip(0), torch.full_like(values, 0.25)])[None, :, None, :]  # (1, 3, 1, 7)
    image = to_uint8(rgb)
    assert image.shape == (1, 1, 7, 3) and image.dtype == np.uint8
    np.testing.assert_array_equal(image[0, 0, :, 2], expected)  # red last
    np.testing.assert_array_equal(image[0, 0, :, 1], expected[::-1])
    np.testing.assert_array_equal(image[0, 0, :, 0], 64)  # 63.75 + 0.5 -> 64
    assert to_uint8(rgb.expand(3, -1, -1, -1)).shape == (3, 1, 7, 3)
