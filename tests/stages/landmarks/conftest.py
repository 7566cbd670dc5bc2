"""Shared fixtures: the astronaut photo's face (scikit-image, public domain), cropped and upscaled."""

import cv2
import numpy as np
import pytest
from skimage import data

# The astronaut's face in skimage.data.astronaut() (512 x 512): the mesh spans about x 181-270, y 72-177
# (about 60 px between the outer eye corners). FACE_BOX is a hand-drawn box around the face (x0, y0, x1, y1,
# px of the original image) with a few px of slack; CROP the region cut out around it.
FACE_BOX = (170, 60, 280, 190)
CROP = (140, 30, 310, 210)
SCALE = 3


def to_upscaled(xy):
    """Original-image px -> px of the CROP upscaled by SCALE with cv2.resize (pixel centres map as
    x' + 0.5 = SCALE (x - x0 + 0.5))."""
    return (np.asarray(xy, float) - CROP[:2] + 0.5) * SCALE - 0.5


@pytest.fixture(scope="session")
def face():
    """The astronaut's face: CROP of the photo upscaled x3 (bicubic) -> (540, 510, 3) uint8 RGB."""
    x0, y0, x1, y1 = CROP
    return cv2.resize(data.astronaut()[y0:y1, x0:x1], None, fx=SCALE, fy=SCALE, interpolation=cv2.INTER_CUBIC)
