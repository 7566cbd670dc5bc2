"""Frame filters for packs on the real-texture clip (fixtures/realface: the astronaut's face with its true
mesh per frame): a blurred frame, eyes and mouth covered, a face cut by the border, no face, a turned
head; head angles from known rotations; the Laplacian sharpness."""

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stages.landmarks.correspondence import layout_from_mesh, load_correspondence
from stages.layout import load_layout
from stages.packbuild.filters import CAUSES, KEEP, cause_counts, classify_frames, head_angles, laplacian_sharpness, measure_frames

REALFACE = Path(__file__).resolve().parents[3] / "fixtures" / "realface"
FRAMES = 10
LAYOUT = load_layout("zhang134")


@pytest.fixture(scope="module")
def clip():
    """The first FRAMES frames of astro.mp4 and their true layout points (N, 2) px."""
    import av

    with av.open(str(REALFACE / "astro.mp4")) as container:
        frames = np.stack([f.to_ndarray(format="rgb24") for _, f in zip(range(FRAMES), container.decode(video=0))])
    with np.load(REALFACE / "astro_truth.npz", allow_pickle=False) as truth:
        mesh = truth["points"][:FRAMES]
    return frames, layout_from_mesh(mesh, load_correspondence("zhang134_mediapipe", layout=LAYOUT))


def cover(image, points, names, value):
    """Paint the box around the named points (grown by 4 px) with ``value``."""
    p = points[list(LAYOUT.indices(names))]
    x0, y0 = np.floor(p.min(0)).astype(int) - 4
    x1, y1 = np.ceil(p.max(0)).astype(int) + 4
    image[y0:y1, x0:x1] = value


def test_head_angles_recovers_known_rotations_through_scale_and_translation():
    truth = np.array([[20.0, -5.0, 3.0], [-12.0, 8.0, -15.0], [0.0, 0.0, 0.0]])
    matrix = np.tile(np.eye(4), (4, 1, 1))
    matrix[:3, :3, :3] = 1.7 * Rotation.from_euler("YXZ", truth, degrees=True).as_matrix()
    matrix[:3, :3, 3] = (1.0, -2.0, -40.0)
    matrix[3, :3, :3] = 5.0  # garbage where there is no face
    got = head_angles(matrix, np.array([True, True, True, False]))
    np.testing.assert_allclose(got[:3], truth, atol=1e-9)
    np.testing.assert_array_equal(got[3], 0.0)


def test_laplacian_sharpness_drops_with_blur_and_follows_the_mask():
    rng = np.random.default_rng(0)
    image = cv2.GaussianBlur(rng.uniform(0, 255, (64, 64)), (0, 0), 1.0)
    blurred = cv2.GaussianBlur(image, (0, 0), 2.0)
    assert laplacian_sharpness(blurred) < 0.2 * laplacian_sharpness(image)
    half = np.zeros((64, 64), bool)
    half[:, :32] = True
    flat = image.copy()
    flat[:, 32:] = 0
    assert laplacian_sharpness(flat, half[:, :] & (np.arange(64) < 30)) == pytest.approx(
        laplacian_sharpness(image[:, :31]), rel=0.1
    )
    assert laplacian_sharpness(image, np.zeros((64, 64), bool)) == 0.0


def test_each_bad_frame_is_rejected_for_its_own_cause(clip):
    frames, points = clip
    frames, points = frames.copy(), points.copy()
    valid = np.ones(FRAMES, bool)
    angles = np.zeros((FRAMES, 3))
    frames[2] = cv2.GaussianBlur(frames[2], (0, 0), 3.0)  # motion blur / defocus
    cover(frames[3], points[3], [f"eye_{s}_{k}" for s in "lr" for k in range(12)], (20, 20, 20))  # sunglasses
    cover(frames[4], points[4], [f"mouth_outer_{k}" for k in range(16)], (128, 128, 128))  # microphone
    valid[5] = False  # no face found
    angles[6] = (28.0, 0.0, 0.0)  # head turned
    angles[7] = (0.0, 0.0, -19.0)  # head tilted
    points[8] += (0.0, 200.0)  # chin below the frame
    measured = measure_frames([(0, frames[:5]), (5, frames[5:])], points, valid, LAYOUT)
    cause, scores = classify_frames(
        valid=valid,
        inside=measured["inside"],
        angles=angles,
        sharpness=measured["sharpness"],
        colours=measured["colours"],
        max_yaw=20.0,
        max_pitch=15.0,
        max_roll=15.0,
        min_sharpness=0.5,
        max_colour_change=10.0,
    )
    expected = [KEEP, KEEP, "blur", "occlusion", "occlusion", "no_face", "head_pose", "head_pose", "out_of_frame", KEEP]
    assert cause.tolist() == [e if e == KEEP else CAUSES.index(e) for e in expected]
    assert cause_counts(cause).tolist() == [1, 1, 2, 1, 2]
    kept = cause == KEEP
    assert np.all(scores["sharpness_rel"][kept] > 0.7) and scores["sharpness_rel"][2] < 0.5
    assert np.all(scores["colour_change"][kept] < 3.0)
    # teeth: the astronaut smiles with her teeth showing
    assert np.all(measured["teeth_fraction"][kept] > 0.3)


def test_classify_frames_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="angles"):
        classify_frames(
            valid=np.ones(3, bool),
            inside=np.ones(3, bool),
            angles=np.zeros((2, 3)),
            sharpness=np.ones(3),
            colours=np.zeros((3, 3, 3)),
            max_yaw=1,
            max_pitch=1,
            max_roll=1,
            min_sharpness=0.5,
            max_colour_change=10,
        )
