"""A PNG's image data checked before OpenCV decodes it: extra data is refused, not decoded with
libpng's warning line on stderr."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from stages.image_header import image_size
from tests.stages.image_files import rgb_png

RGB = np.random.default_rng(3).integers(0, 256, (13, 11, 3), dtype=np.uint8)


@pytest.mark.parametrize("interlaced", [False, True])
def test_a_whole_png_is_accepted_and_decodes_to_its_pixels(tmp_path, interlaced, capfd):
    path = tmp_path / "a.png"
    rgb_png(path, RGB, interlaced=interlaced)
    assert image_size(path, max_pixels=1000, verify=True) == (11, 13)
    np.testing.assert_array_equal(cv2.imread(str(path))[..., ::-1], RGB)
    assert "libpng" not in capfd.readouterr().err


@pytest.mark.parametrize("damage", [{"extra": b"\0" * 40}, {"after_end": b"trailing compressed bytes"}])
def test_a_png_with_extra_image_data_is_refused_before_decoding(tmp_path, damage, capfd):
    path = tmp_path / "a.png"
    rgb_png(path, RGB, **damage)
    assert image_size(path, max_pixels=1000) == (11, 13)  # the header alone is fine
    assert image_size(path, max_pixels=1000, verify=True) is None
    assert "libpng" not in capfd.readouterr().err
