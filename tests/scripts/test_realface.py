"""Real-texture ground-truth clips (lab/realface): the renderer reproduces the photo, the
truth follows the analytic projection, MediaPipe finds the truth points on rendered frames,
same seed same clip, and the committed fixture is what the generator makes."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from matplotlib.path import Path as PolygonPath

from stages.eigen.facegen.render import project
from scripts.make_realface import main
from lab.realface.clip import fit_real_face, make_clip, pose, render_state
from lab.realface.expression import EXPRESSIONS, deform
from lab.realface.landmarks import (
    LIPS_INNER_LOWER,
    LIPS_INNER_UPPER,
    MOUTH_CORNERS,
    NOSE_TIP,
    UPPER_LIDS,
    detect,
    inner_lip_polygon,
    open_landmarker,
    point_groups,
)
from lab.realface.mesh import MOUTH_OPEN_MAX, build_mesh
from lab.realface.motion import ANGLE_LIMITS_DEG, make_motion
from lab.realface.photo import source_photo
from lab.realface.render import interpolate, rasterize
from stages.video import VideoDecode, probe

REPO = Path(__file__).resolve().parents[2]
FIXTURE = REPO / "fixtures" / "realface"
ZERO = np.zeros(3)


@pytest.fixture(scope="module")
def face():
    return fit_real_face(256)


def _outside_mouth(face, grow: int) -> np.ndarray:
    """``(S, S)`` bool: pixels more than ``grow`` px from the inner-lip polygon (the mouth
    opening, where the painted cavity shows)."""
    s = face.mesh.size
    mask = np.zeros((s, s), np.uint8)
    cv2.fillPoly(mask, [np.round(face.landmarks[list(inner_lip_polygon()), :2]).astype(np.int32)], 1)
    return cv2.dilate(mask, np.ones((2 * grow + 1, 2 * grow + 1), np.uint8)) == 0


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0**2 / max(mse, 1e-12)))


def test_identity_pose_reproduces_the_photo(face):
    keep = _outside_mouth(face, 3)
    exact = render_state(face, ZERO, ZERO, ZERO, supersample=1)[0]
    assert np.abs(exact.image.astype(int) - face.photo)[keep].max() <= 1
    smooth = render_state(face, ZERO, ZERO, ZERO, supersample=2)[0]
    assert _psnr(smooth.image[keep], face.photo[keep]) > 35.0
    np.testing.assert_allclose(exact.points, face.landmarks[:, :2], atol=1e-9)
    assert exact.visible.all()


def test_backdrop_stays_while_the_head_turns_in_front_of_it(face):
    """With a backdrop: at rest the frame is the photo; turned, the head moves and the background
    (the frame's bottom corners, beyond the head's rings) stays; the coverage is the head."""
    from dataclasses import replace
    from lab.realface.mesh import clean_plate

    staged = replace(face, backdrop=clean_plate(face.photo, face.mesh))
    rest = render_state(staged, ZERO, ZERO, ZERO, supersample=1)[0]
    head = _outside_mouth(face, 3) & (rest.coverage == 1)
    assert head.mean() > 0.3 and np.abs(rest.image.astype(int) - face.photo)[head].max() <= 1
    behind = cv2.dilate((rest.coverage > 0).astype(np.uint8), np.ones((3, 3), np.uint8)) == 0  # the plate is the photo there
    np.testing.assert_array_equal(rest.image[behind], face.photo[behind])
    turned = render_state(staged, ZERO, np.array([25.0, 0.0, 0.0]), ZERO, supersample=1)[0]
    s = face.mesh.size
    corners = (slice(s - 12, s), slice(0, 12)), (slice(s - 12, s), slice(s - 12, s))
    for corner in corners:
        assert rest.coverage[corner].max() == 0
        np.testing.assert_array_equal(turned.image[corner], staged.backdrop[corner])
    nose = np.round(rest.points[NOSE_TIP]).astype(int)
    assert rest.coverage[nose[1], nose[0]] == 1.0 and 0.0 <= turned.coverage.min() and turned.coverage.max() <= 1.0
    assert np.abs(turned.image.astype(int) - rest.image).mean() > 2.0


def test_perspective_correct_interpolation_lands_on_the_pixel_centre(face):
    vertices = deform(face.mesh, face.basis, np.array([0.7, 0.4, 0.6]))
    R, t = pose(face, np.array([18.0, -8.0, 6.0]), np.array([3.0, -2.0, 10.0]))
    px, z = project(vertices, R, t, face.mesh.intrinsics)
    size = face.mesh.size
    raster = rasterize(px, z, face.mesh.skin, (size, size))
    assert len(raster.pixel) > 0.97 * size * size  # the ring reaches past the border
    cam = interpolate(raster, vertices @ R.T + t, np.ones(len(vertices)))
    back = cam @ face.mesh.intrinsics.T
    centres = np.column_stack([raster.pixel % size, raster.pixel // size])
    np.testing.assert_allclose(back[:, :2] / back[:, 2:], centres, atol=1e-6)
    np.testing.assert_allclose(1.0 / cam[:, 2], raster.inv_depth.ravel()[raster.pixel], rtol=1e-9)


def test_rasterizer_coverage_and_nearest_wins():
    px = np.array([[2.3, 1.7], [17.6, 4.2], [6.1, 15.8], [1.2, 1.3], [18.1, 1.4], [10.3, 18.2]])
    tris = np.array([[0, 1, 2], [3, 4, 5]])
    ys, xs = np.mgrid[0:20, 0:20]
    centres = np.column_stack([xs.ravel(), ys.ravel()])
    inside = [PolygonPath(px[t]).contains_points(centres) for t in tris]
    for near, depth in ((0, np.array([1.0, 1, 1, 2, 2, 2])), (1, np.array([3.0, 3, 3, 2, 2, 2]))):
        raster = rasterize(px, depth, tris, (20, 20))
        owner = np.full(400, -1)
        owner[raster.pixel] = (raster.corners[:, 0] == 3).astype(int)[raster.span]  # which triangle
        np.testing.assert_array_equal(owner >= 0, inside[0] | inside[1])
        np.testing.assert_array_equal(owner[inside[near]], near)


def test_yaw_moves_the_nose_tip_as_projected(face):
    yaw = np.deg2rad(12.0)
    frame = render_state(face, ZERO, np.array([12.0, 0.0, 0.0]), ZERO)[0]
    ry = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
    cam = ry @ face.mesh.vertices[NOSE_TIP] + face.mesh.head_centre
    expected = (face.mesh.intrinsics @ cam)[:2] / cam[2]
    np.testing.assert_allclose(frame.points[NOSE_TIP], expected, atol=1e-9)
    assert expected[0] < face.landmarks[NOSE_TIP, 0] - 5  # positive yaw turns the nose to image left
    # the texture moved with it: the nose patch of the photo is found where the truth says
    nose = np.round(face.landmarks[NOSE_TIP, :2]).astype(int)
    r = 10
    patch = cv2.cvtColor(face.photo, cv2.COLOR_RGB2GRAY)[nose[1] - r : nose[1] + r + 1, nose[0] - r : nose[0] + r + 1]
    gray = cv2.cvtColor(frame.image, cv2.COLOR_RGB2GRAY)
    score = cv2.matchTemplate(gray, patch, cv2.TM_CCOEFF_NORMED)
    y, x = np.unravel_index(np.argmax(score), score.shape)
    found = np.array([x + r, y + r]) + (face.landmarks[NOSE_TIP, :2] - nose)
    assert np.linalg.norm(found - frame.points[NOSE_TIP]) < 1.5


def test_mediapipe_finds_the_truth_points_on_rendered_frames(face):
    """Texture and geometry agree: MediaPipe on a rendered frame lands on the truth points (within
    its own error, larger on the face outline and under the synthetic expressions, which its face
    model reads its own way; measured at 256 px: 0.9 px rigid, 2.4 px with expressions)."""
    states = [(ZERO, np.array([12.0, -6.0, 5.0]), 1.5, 1.2), (np.array([0.5, 0.5, 0.6]), np.array([-10.0, 5.0, -4.0]), 3.5, 1.5)]
    groups = point_groups()
    with open_landmarker() as landmarker:
        for params, angles, inner_px, eyes_px in states:
            frame = render_state(face, params, angles, np.array([2.0, -1.0, 5.0]))[0]
            found = detect(landmarker, frame.image)
            assert found is not None
            err = np.linalg.norm(found[:, :2] - frame.points, axis=1)
            inner = np.setdiff1d(np.flatnonzero(frame.visible), groups["oval"])
            assert np.mean(err[inner]) < inner_px
            assert np.mean(err[groups["eyes"]]) < eyes_px


def test_expressions_move_what_they_name(face):
    mesh, D = face.mesh, face.mesh.eye_px * face.mesh.mm_per_px
    rest = mesh.vertices
    opened = deform(mesh, face.basis, np.array([1.0, 0.0, 0.0]))
    lip_top, lip_bottom = LIPS_INNER_UPPER[5], LIPS_INNER_LOWER[5]
    assert np.allclose(opened[lip_top], rest[lip_top])
    assert opened[lip_bottom, 1] - rest[lip_bottom, 1] == pytest.approx(MOUTH_OPEN_MAX * D)
    raised = deform(mesh, face.basis, np.array([0.0, 1.0, 0.0]))
    assert np.allclose(raised[list(UPPER_LIDS)], rest[list(UPPER_LIDS)])
    assert np.all(raised[[105, 334], 1] < rest[[105, 334], 1] - 0.05 * D)
    smiled = deform(mesh, face.basis, np.array([0.0, 0.0, 1.0]))
    move = smiled[list(MOUTH_CORNERS)] - rest[list(MOUTH_CORNERS)]
    assert move[0, 0] < 0 < move[1, 0] and np.all(move[:, 1] < -0.05 * D)
    with pytest.raises(ValueError, match="params"):
        deform(mesh, face.basis, np.array([1.5, 0.0, 0.0]))


def test_motion_is_seeded_and_within_limits():
    params, angles, shift = make_motion(200, seed=3, fps=25)
    again = make_motion(200, seed=3, fps=25)
    other = make_motion(200, seed=4, fps=25)
    for a, b in zip((params, angles, shift), again):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(params, other[0])
    assert np.all(params[0] == 0) and np.all(angles[0] == 0) and np.all(shift[0] == 0)
    assert np.all(np.abs(angles) <= ANGLE_LIMITS_DEG)
    assert np.all(params.max(axis=0) > 0.4)  # every expression happens
    mouth = np.flatnonzero(np.diff(np.concatenate([[0], params[:, EXPRESSIONS.index("mouth_open")] > 0, [0]])))
    assert np.all((np.diff(mouth)[::2] >= 3) & (np.diff(mouth)[::2] <= 8))


def test_same_seed_same_clip_and_the_lossless_option(tmp_path):
    a = make_clip(tmp_path / "a", frames=3, seed=7, size=160)
    b = make_clip(tmp_path / "b", frames=3, seed=7, size=160)
    assert [p.read_bytes() for p in a] == [p.read_bytes() for p in b]
    assert main(["--out", str(tmp_path / "c"), "--frames", "3", "--seed", "7", "--size", "160", "--lossless"]) == 0
    assert (tmp_path / "c" / "astro_truth.npz").read_bytes() == a[1].read_bytes()
    decoded = VideoDecode().process(0, 3, {"video": str(tmp_path / "c" / "astro.mkv")}, {}, None)["frames"]
    face = fit_real_face(160)
    params, angles, shift = make_motion(3, seed=7, fps=25)
    for f in range(3):
        np.testing.assert_array_equal(decoded[f], render_state(face, params[f], angles[f], shift[f])[0].image)


def test_committed_fixture_is_what_the_generator_makes():
    with np.load(FIXTURE / "astro_truth.npz", allow_pickle=False) as z:
        truth = {k: z[k] for k in z.files}
    frames, size = len(truth["points"]), int(truth["frame_size"][0])
    info = probe(FIXTURE / "astro.mp4")
    assert (info.frames, info.width, info.height, info.fps) == (frames, size, size, 25.0)
    face = fit_real_face(size)
    # MediaPipe's float32 inference may differ in the last bits on another CPU: 0.05 px / mm slack
    np.testing.assert_allclose(face.landmarks, truth["source_landmarks"], atol=0.05)
    params, angles, shift = make_motion(frames, seed=int(truth["seed"]), fps=float(truth["fps"]))
    np.testing.assert_array_equal(params, truth["expression"])
    np.testing.assert_array_equal(angles, truth["angles_deg"])
    decoded = VideoDecode().process(0, frames, {"video": str(FIXTURE / "astro.mp4")}, {}, None)["frames"]
    for f in range(frames):
        vertices = deform(face.mesh, face.basis, params[f])
        R, t = pose(face, angles[f], shift[f])
        np.testing.assert_allclose(R, truth["R"][f], atol=1e-12)
        np.testing.assert_allclose(t, truth["tvec"][f], atol=0.05)
        np.testing.assert_allclose(vertices[:478], truth["points3d"][f], atol=0.05)
        np.testing.assert_allclose(project(vertices[:478], R, t, truth["intrinsics"])[0], truth["points"][f], atol=0.05)
        if f in (0, frames // 2, frames - 1):
            frame = render_state(face, params[f], angles[f], shift[f])[0]
            assert np.sum(frame.visible != truth["visible"][f]) <= 3
            assert _psnr(decoded[f], frame.image) > 38.0
    rvec = np.stack([cv2.Rodrigues(R)[0].ravel() for R in truth["R"]])
    np.testing.assert_allclose(rvec, truth["rvec"], atol=1e-12)


def test_mediapipe_pixels_have_their_origin_at_the_top_left_pixel_centre(face):
    """An image upscaled 2x by pixel replication holds the same content at ``x2 = 2 x + 0.5``
    (centre origin; ``2 x`` with a corner origin): the landmarks follow the centre origin."""
    doubled = np.repeat(np.repeat(face.photo, 2, axis=0), 2, axis=1)
    with open_landmarker() as landmarker:
        found = detect(landmarker, doubled)
    offset = np.mean(found[:, :2] - 2 * face.landmarks[:, :2], axis=0)
    assert np.all(np.abs(offset - 0.5) < 0.25), offset


def test_bad_input_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="even"):
        source_photo(255)
    with pytest.raises(ValueError, match=r"\(478, 3\)"):
        build_mesh(np.zeros((468, 3)), size=256)
    with pytest.raises(ValueError, match="no such file"):
        open_landmarker(model_path=tmp_path / "missing.task")
