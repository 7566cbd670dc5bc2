"""Stages landmarks.mediapipe and landmarks.layout on a short clip made here (the astronaut's face moving
by known whole pixels per frame, then a frame without a face)."""

import logging

import cv2
import numpy as np
import pytest

from runner.stage import Context, StageError
from stages.landmarks.landmarker import BLENDSHAPE_NAMES
from stages.landmarks.stage import FaceLandmarks, LayoutPoints
from stages.layout import load_layout
from tests.memory_stream import MemoryStream

SHIFTS = [(0, 0), (6, 3), (12, 6), (18, 9), (24, 12)]


def clip(face):
    """(6, 600, 600, 3): the face at half size (mesh ~135 px wide, so that the crop around it is smaller than
    the frame) pasted at (150, 140) + SHIFTS[t] on grey, then a grey frame."""
    face = cv2.resize(face, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    frames = np.full((len(SHIFTS) + 1, 600, 600, 3), 100, np.uint8)
    h, w = face.shape[:2]
    for t, (dx, dy) in enumerate(SHIFTS):
        frames[t, 140 + dy : 140 + dy + h, 150 + dx : 150 + dx + w] = face
    return frames


@pytest.fixture(scope="module")
def landmarks(face):
    done = []
    ctx = Context(device="cpu", files_dir=lambda port: None, progress=done.append)
    stream = MemoryStream(clip(face), chunk=4)
    bundle = FaceLandmarks().run({"frames": stream}, {}, ctx)["landmarks"]
    assert sum(done) == len(SHIFTS) + 1 and stream.reads == 2
    return bundle


def test_bundle_keys_shapes_and_the_frame_without_a_face(landmarks):
    t = len(SHIFTS) + 1
    assert landmarks["xy"].shape == (t, 478, 2) and landmarks["xy"].dtype == np.float64
    assert landmarks["z"].shape == (t, 478) and landmarks["blendshapes"].shape == (t, 52)
    assert landmarks["blendshapes"].dtype == np.float32
    assert tuple(landmarks["blendshape_names"]) == BLENDSHAPE_NAMES
    assert landmarks["matrix"].shape == (t, 4, 4)
    np.testing.assert_array_equal(landmarks["valid"], [True] * len(SHIFTS) + [False])
    np.testing.assert_array_equal(landmarks["faces"], [1] * len(SHIFTS) + [0])
    assert np.isnan(landmarks["xy"][-1]).all() and np.isnan(landmarks["face_width_px"][-1])
    np.testing.assert_array_equal(landmarks["matrix"][-1], np.eye(4))
    np.testing.assert_array_equal(landmarks["size"], [600, 600])
    width = landmarks["face_width_px"][:-1]
    assert (width > 100).all() and (width < 165).all()  # the mesh spans ~90 px of the photo, x1.5


def test_points_move_by_the_known_shift(landmarks):
    xy = landmarks["xy"]
    for t, shift in enumerate(SHIFTS):
        moved = (xy[t] - xy[0]).mean(axis=0)
        np.testing.assert_allclose(moved, shift, atol=0.4)
    # after frame 0 the face is searched in the crop around the previous one
    assert (landmarks["region"][1 : len(SHIFTS), 2] < 600).all() and (landmarks["region"][1 : len(SHIFTS), :2] > 0).all()


def test_layout_points_move_by_the_known_shift(landmarks):
    points = LayoutPoints().run({"landmarks": landmarks}, {}, Context(device="cpu", files_dir=lambda p: None))["points"]
    layout = load_layout("zhang134")
    assert tuple(points["names"]) == layout.point_names
    assert points["xy"].shape == (len(SHIFTS) + 1, 134, 2) and points["confidence"].dtype == np.float32
    np.testing.assert_array_equal(points["valid"].all(axis=1), landmarks["valid"])
    assert not points["valid"][-1].any() and np.isnan(points["xy"][-1]).all()
    for t, shift in enumerate(SHIFTS):
        np.testing.assert_allclose((points["xy"][t] - points["xy"][0]).mean(axis=0), shift, atol=0.4)
    # viewer's-left points left of their mirrored partners, the hairline above the brows, the chin lowest
    xy = points["xy"][0]
    assert xy[layout.index("eye_l_6"), 0] < xy[layout.index("eye_l_0"), 0] < xy[layout.index("eye_r_0"), 0]
    assert xy[layout.index("hairline_2"), 1] < xy[layout.index("brow_l_6"), 1] < xy[layout.index("eye_l_3"), 1]
    assert xy[layout.index("contour_8"), 1] == xy[:, 1].max()


def test_no_face_in_any_frame_is_a_stage_error():
    stream = MemoryStream(np.full((3, 120, 160, 3), 128, np.uint8))
    with pytest.raises(StageError, match="no face found in any of 3 frames"):
        FaceLandmarks().run({"frames": stream}, {"search_tiles": False}, Context(device="cpu", files_dir=lambda p: None))


def test_small_face_warns_with_its_size(face, caplog):
    frames = np.full((1, 600, 600, 3), 100, np.uint8)
    frames[0, 20 : 20 + face.shape[0], 10 : 10 + face.shape[1]] = face
    ctx = Context(device="cpu", files_dir=lambda p: None, log=logging.getLogger("test.landmarks"))
    with caplog.at_level(logging.INFO, logger="test.landmarks"):
        bundle = FaceLandmarks().run({"frames": MemoryStream(frames)}, {"min_face_px": 400.0}, ctx)["landmarks"]
    width = bundle["face_width_px"][0]
    assert any(r.levelno == logging.WARNING and f"smallest {width:.1f} px" in r.getMessage() for r in caplog.records)
    assert any("face in 1 of 1 frames" in r.getMessage() for r in caplog.records)


def test_bad_correspondence_is_a_stage_error(tmp_path, landmarks):
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: bad\nlayout: zhang134\nmesh_vertices: 478\npoints: {chin: 152}\n")
    with pytest.raises(StageError, match="parameter 'correspondence'.*no entry for layout point"):
        LayoutPoints().run(
            {"landmarks": landmarks}, {"correspondence": str(bad)}, Context(device="cpu", files_dir=lambda p: None)
        )
