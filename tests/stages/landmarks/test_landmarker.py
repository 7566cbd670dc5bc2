"""The Face Landmarker wrapper: points on a real face, the pixel convention, no face, the model check."""

import cv2
import mediapipe as mp
import numpy as np
import pytest
from skimage import data

from stages.landmarks.landmarker import (
    BLENDSHAPE_NAMES,
    MODEL_PATH,
    N_MESH,
    Landmarker,
    crop_around,
    tiles,
    verify_model,
)
from tests.stages.landmarks.conftest import CROP, FACE_BOX, to_upscaled


@pytest.fixture(scope="module")
def landmarker():
    with Landmarker() as lm:
        yield lm


def test_astronaut_mesh_inside_face_box(landmarker, face):
    landmarker.reset()
    mesh = landmarker.detect(face)
    assert mesh.valid and mesh.faces == 1
    assert mesh.xy.shape == (N_MESH, 2) and mesh.z.shape == (N_MESH,)
    lo, hi = to_upscaled(FACE_BOX[:2]), to_upscaled(FACE_BOX[2:])
    assert (mesh.xy >= lo).all() and (mesh.xy <= hi).all()
    assert np.isfinite(mesh.z).all() and mesh.z.std() > 5  # px-scale relative depth
    assert ((mesh.blendshapes >= 0) & (mesh.blendshapes <= 1)).all()
    assert abs(np.linalg.det(mesh.matrix[:3, :3]) - 1) < 0.1  # rotation part of a rigid matrix
    # the viewer's-left outer eye corner (33) is left of the viewer's-right one (263)
    assert mesh.xy[33, 0] < mesh.xy[263, 0]


def test_blendshape_names_are_the_models():
    from mediapipe.tasks.python import BaseOptions, vision

    options = vision.FaceLandmarkerOptions(
        base_options=BaseOptions(model_asset_path=str(MODEL_PATH)), output_face_blendshapes=True
    )
    with vision.FaceLandmarker.create_from_options(options) as task:
        result = task.detect(mp.Image(image_format=mp.ImageFormat.SRGB, data=data.astronaut()))
    assert tuple(c.category_name for c in result.face_blendshapes[0]) == BLENDSHAPE_NAMES


def test_pixel_origin_is_the_centre_of_the_top_left_pixel(landmarker):
    """Upscaling by s maps pixel centres x -> s (x + 0.5) - 0.5 (OpenCV); the mesh must follow that map.
    Were the points reported with the origin at the pixel corner, they would be off by (1 - s) / 2 = -1.5 px."""
    x0, y0, x1, y1 = CROP
    crop = data.astronaut()[y0:y1, x0:x1]
    s = 4
    landmarker.reset()
    small = landmarker.detect(np.ascontiguousarray(crop)).xy
    landmarker.reset()
    large = landmarker.detect(cv2.resize(crop, None, fx=s, fy=s, interpolation=cv2.INTER_CUBIC)).xy
    offset = (large - (s * (small + 0.5) - 0.5)).mean(axis=0)
    assert np.abs(offset).max() < 0.5, offset


def test_integer_shift_moves_points_by_the_shift(landmarker, face):
    """Whole-pixel translation inside a larger canvas: the points move by exactly the shift (within the
    model's noise), whichever region (frame, crop) the face is found in."""
    canvas = np.full((600, 600, 3), 90, np.uint8)
    found = []
    for dx, dy in [(10, 20), (47, 33)]:
        frame = canvas.copy()
        frame[dy : dy + face.shape[0], dx : dx + face.shape[1]] = face
        landmarker.reset()
        found.append(landmarker.detect(frame).xy - (dx, dy))
    assert np.abs(found[1] - found[0]).mean() < 0.3


def test_no_face_is_invalid(landmarker):
    landmarker.reset()
    mesh = landmarker.detect(np.full((256, 320, 3), 128, np.uint8))
    assert not mesh.valid and mesh.faces == 0
    assert np.isnan(mesh.xy).all() and np.isnan(mesh.z).all()
    np.testing.assert_array_equal(mesh.matrix, np.eye(4))
    np.testing.assert_array_equal(mesh.region, [0, 0, 320, 256])


def test_small_face_on_a_large_canvas_is_found_in_tiles_then_in_the_crop():
    """The detector misses the astronaut (face ~90 px) on a 1024 x 1024 canvas; tiles find it, and the next
    frame is found in the crop around it."""
    canvas = np.full((1024, 1024, 3), 110, np.uint8)
    canvas[300:812, 340:852] = data.astronaut()
    with Landmarker(search_tiles=False) as plain:
        assert not plain.detect(canvas).valid
    with Landmarker() as lm:
        first = lm.detect(canvas)
        second = lm.detect(canvas)
    assert first.valid and second.valid
    assert first.region[2] == 512 and second.region[2] < 512  # a tile, then the crop
    assert np.abs(second.xy - first.xy).mean() < 1.0


def test_crop_around_stays_inside_the_image():
    np.testing.assert_array_equal(crop_around(np.array([10.0, 20, 40, 60]), scale=2.0, size=(200, 100)), [0, 0, 80, 80])
    np.testing.assert_array_equal(crop_around(np.array([100.0, 40, 120, 60]), scale=3.0, size=(200, 100)), [80, 20, 60, 60])
    np.testing.assert_array_equal(crop_around(np.array([0.0, 0, 150, 90]), scale=3.0, size=(200, 100)), [0, 0, 200, 100])


def test_tiles_cover_the_image_with_half_overlap():
    regions = np.array(tiles((200, 120)))
    assert (regions[:, 2] == 60).all() and (regions[:, 3] == 60).all()
    covered = np.zeros((120, 200), bool)
    for x0, y0, w, h in regions:
        covered[y0 : y0 + h, x0 : x0 + w] = True
    assert covered.all()
    assert set(regions[:, 0]) == {0, 30, 60, 90, 120, 140} and set(regions[:, 1]) == {0, 30, 60}


def test_damaged_model_is_refused(tmp_path):
    damaged = tmp_path / "face_landmarker.task"
    blob = bytearray(MODEL_PATH.read_bytes())
    blob[1000] ^= 0xFF
    damaged.write_bytes(bytes(blob))
    with pytest.raises(ValueError, match="sha256"):
        verify_model(damaged)
    with pytest.raises(ValueError, match="cannot read"):
        verify_model(tmp_path / "missing.task")
    assert verify_model() == MODEL_PATH


def test_options_are_checked():
    with pytest.raises(ValueError, match="select"):
        Landmarker(select="first")
    with pytest.raises(ValueError, match="crop_scale"):
        Landmarker(crop_scale=0.5)


@pytest.mark.parametrize("select, expected", [("largest", "large"), ("central", "small")])
def test_several_faces_choose_by_the_rule(select, expected):
    """Two astronaut faces, a large one in a corner and a small one at the centre of the frame."""
    x0, y0, x1, y1 = CROP
    small = np.ascontiguousarray(data.astronaut()[y0:y1, x0:x1])  # mesh ~90 px wide
    large = cv2.resize(small, None, fx=1.6, fy=1.6, interpolation=cv2.INTER_CUBIC)
    frame = np.full((560, 720, 3), 100, np.uint8)
    frame[10 : 10 + large.shape[0], 10 : 10 + large.shape[1]] = large
    cy, cx = 280 - small.shape[0] // 2, 360 - small.shape[1] // 2 + 60
    frame[cy : cy + small.shape[0], cx : cx + small.shape[1]] = small
    with Landmarker(select=select) as lm:
        mesh = lm.detect(frame)
    assert mesh.valid and mesh.faces == 2
    width = np.ptp(mesh.xy[:, 0])
    centre_x = mesh.xy[:, 0].mean()
    if expected == "large":
        assert width > 120 and centre_x < 300
    else:
        assert width < 110 and centre_x > 300


def _two_faces(left_scale: float, right_scale: float) -> np.ndarray:
    """The astronaut's face twice on a 640 x 420 frame, centres at x 160 and 480, each scaled."""
    x0, y0, x1, y1 = CROP
    face = np.ascontiguousarray(data.astronaut()[y0:y1, x0:x1])
    frame = np.full((420, 640, 3), 100, np.uint8)
    for scale, cx in ((left_scale, 160), (right_scale, 480)):
        image = cv2.resize(face, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
        h, w = image.shape[:2]
        frame[210 - h // 2 : 210 - h // 2 + h, cx - w // 2 : cx - w // 2 + w] = image
    return frame


def test_the_face_chosen_first_is_followed_when_another_grows():
    """Regression (two people side by side, the robustness campaign on real clips): the rule
    (largest) chooses the left face in the first frame; when the right one becomes the larger,
    the left one is still followed. A crop as large as the frame (crop_scale 5) searches both
    faces every frame, as a wide crop around a face next to another does."""
    with Landmarker(select="largest", crop_scale=5.0) as lm:
        first = lm.detect(_two_faces(1.4, 1.2))
        assert first.valid and first.faces == 2 and first.xy[:, 0].mean() < 320
        for _ in range(2):
            mesh = lm.detect(_two_faces(1.2, 1.4))
            assert mesh.valid and mesh.faces == 2
            assert mesh.xy[:, 0].mean() < 320  # still the left face
        lm.reset()  # no previous face: the rule chooses again, the right face is now the largest
        assert lm.detect(_two_faces(1.2, 1.4)).xy[:, 0].mean() > 320
