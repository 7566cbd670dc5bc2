"""Tracker tests against a texture moved by known sub-pixel similarity and affine transforms."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from runner.stage import StageError
from stages.geometry.correlation import correlation_peaks, local_affines, sample_patches
from stages.geometry.first_frame_points import read_first_frame_points
from stages.geometry.ncc_tracker import NCCTracker
from stages.geometry.track import CorrelationTrack
from stages.geometry.tracker_options import TrackerOptions
from stages.geometry.tracking import track_points
from stages.layout import load_layout
from tests.stages.geometry.synthetic import MemoryStream, apply, context, moving_clip, texture

N_FRAMES = 40


@pytest.fixture(scope="module")
def clip():
    frames, transforms = moving_clip(N_FRAMES, size=(160, 120), seed=1)
    rng = np.random.default_rng(2)
    init = rng.uniform([25, 25], [135, 95], (12, 2))
    return frames, init, apply(transforms, init)


def test_correlation_peaks_subpixel():
    grid = np.arange(17, dtype=np.float64) - 8
    x0, y0 = 2.3, -1.6
    quadratic = 1.0 - 0.01 * ((grid[None, :] - x0) ** 2 + (grid[:, None] - y0) ** 2)
    offset, peak, _ = correlation_peaks(quadratic[None].astype(np.float32))
    np.testing.assert_allclose(offset[0], [x0, y0], atol=1e-5)
    assert peak[0] == pytest.approx(quadratic.max(), abs=1e-6)


def test_peak_to_sidelobe_ratio_separates_sharp_from_ambiguous():
    grid = np.arange(17, dtype=np.float64) - 8
    rng = np.random.default_rng(0)
    noise = rng.normal(0.0, 0.05, (2, 17, 17))
    sharp = np.maximum(0.0, 1.0 - 0.3 * (grid[None, :] ** 2 + grid[:, None] ** 2)) + noise[0]
    _, _, psr = correlation_peaks(np.stack([sharp, noise[1]]).astype(np.float32))
    mask = np.ones((17, 17), bool)
    mask[np.unravel_index(sharp.argmax(), sharp.shape)[0] - 2 :][:5, 6:11] = False
    side = sharp[mask]
    assert psr[0] == pytest.approx((sharp.max() - side.mean()) / side.std(), rel=1e-3)
    assert psr[0] > 10.0 and psr[1] < 5.0


# measured: ncc 0.049 / 0.110 px, lk 0.066 / 0.135 px (mean / p95)
@pytest.mark.parametrize("method, mean_px, p95_px", [("ncc", 0.065, 0.14), ("lk", 0.09, 0.18)])
def test_tracks_known_motion(clip, method, mean_px, p95_px):
    frames, init, truth = clip
    tracks = track_points(iter(frames), init, method=method)
    assert tracks.xy.shape == (N_FRAMES, len(init), 2) and tracks.valid.shape == (N_FRAMES, len(init))
    error = np.linalg.norm(tracks.xy - truth, axis=2)
    assert tracks.valid.all()
    assert error.mean() < mean_px and np.percentile(error, 95) < p95_px
    assert tracks.confidence.dtype == np.float32 and (tracks.confidence > 0.5).all()


def affine_clip(n_frames: int, *, size: tuple[int, int] = (160, 120), seed: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """A texture turning to 30 degrees while squeezed to 75 % across and stretched 10 % along
    (a head's rotation and foreshortening): frames ``(T, H, W, 3)`` and transforms ``(T, 2, 3)``."""
    width, height = size
    base = texture(height, width, seed=seed)
    centre = np.array([width / 2.0, height / 2.0])
    frames, transforms = [], []
    for t in range(n_frames):
        k = t / (n_frames - 1)
        angle = np.deg2rad(30.0 * k)
        linear = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]) @ np.diag(
            [1.0 - 0.25 * k, 1.0 + 0.1 * k]
        )
        m = np.hstack([linear, (centre - linear @ centre + [3.0 * k, -2.0 * k])[:, None]])
        image = cv2.warpAffine(base, m, size, flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
        frames.append(np.repeat(np.clip(np.rint(image), 0, 255).astype(np.uint8)[..., None], 3, axis=2))
        transforms.append(m)
    return np.stack(frames), np.array(transforms)


def test_warped_first_frame_template_follows_rotation_and_foreshortening():
    frames, transforms = affine_clip(30)
    init = np.random.default_rng(8).uniform([45, 35], [115, 85], (12, 2))
    truth = apply(transforms, init)
    errors = {}
    for method in ("ncc", "lk"):
        tracks = track_points(iter(frames), init, method=method)
        errors[method] = np.linalg.norm(tracks.xy - truth, axis=2)
        assert tracks.valid.all()
    # measured: ncc 0.033 / 0.068 px (mean / p95); frame-to-frame LK drifts to 0.33 / 0.92
    assert errors["ncc"].mean() < 0.05 and np.percentile(errors["ncc"], 95) < 0.09
    assert errors["ncc"].mean() < 0.2 * errors["lk"].mean()


def test_local_affines_recover_an_exact_affine_motion():
    rng = np.random.default_rng(9)
    src = rng.uniform(0, 100, (15, 2))
    linear = np.array([[0.9, -0.3], [0.25, 1.1]])
    dst = src @ linear.T + [4.0, -2.0]
    for exclude_self in (False, True):
        m, b = local_affines(src, dst, np.ones(15), sigma_px=30.0, exclude_self=exclude_self)
        np.testing.assert_allclose(m, np.broadcast_to(linear, (15, 2, 2)), atol=1e-6)
        np.testing.assert_allclose(b, dst, atol=1e-4)
    # one point's own wrong position (8.6 px off) barely moves where its neighbours put it (only
    # through the global affine that the local fits are regularized towards)
    moved = dst.copy()
    moved[3] += (5.0, -7.0)
    _, b = local_affines(src, moved, np.ones(15), sigma_px=30.0, exclude_self=True)
    np.testing.assert_allclose(b[3], dst[3], atol=0.05)


def test_sample_patches_match_cv2_warp_affine():
    image = texture(120, 160, seed=3)
    centres = np.array([[40.3, 50.7], [100.0, 60.25], [80.5, 30.0]])
    linear = np.array([[[1.1, 0.2], [-0.1, 0.9]], [[0.8, -0.4], [0.4, 0.8]], [[1.0, 0.0], [0.0, 1.0]]])
    patches = sample_patches(image, centres, 11, linear)
    for patch, c, m in zip(patches, centres, linear):
        inverse_map = np.hstack([m, (c - m @ [5.0, 5.0])[:, None]])
        expected = cv2.warpAffine(image, inverse_map, (11, 11), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
        np.testing.assert_allclose(patch, expected, atol=1e-2)


def test_edge_template_takes_the_along_edge_position_from_its_neighbours():
    tracker = NCCTracker(TrackerOptions(prior=0.03, prior_frac=1.5))
    rng = np.random.default_rng(10)
    origin = rng.uniform(20, 100, (10, 2))
    tracker.start(np.zeros((120, 160), np.uint8), origin)
    truth = origin + (2.5, -1.5)
    found = truth.copy()
    found[0] += (0.0, 4.0)  # wrong along a vertical edge,
    information = np.tile(np.eye(2) * 0.3, (10, 1, 1))
    information[0] = np.diag([0.3, 0.0])  # whose template pins x only
    combined = tracker.with_neighbours(found, information, np.ones(10, bool))
    np.testing.assert_allclose(combined[0], truth[0], atol=1e-6)
    # a well-textured point keeps most of its own match: prior / (0.3 + prior) of it goes
    found[1] += (1.0, 1.0)
    combined = tracker.with_neighbours(found, information, np.ones(10, bool))
    np.testing.assert_allclose(combined[1] - truth[1], np.full(2, 0.3 / 0.33), atol=0.02)


@pytest.mark.parametrize("method", ["csrt", "kcf", "mosse"])
def test_opencv_trackers_follow_the_motion(clip, method):
    frames, init, truth = clip
    gray = frames[:6, :, :, :1] if method == "kcf" else frames[:6]  # one-channel frames work too
    tracks = track_points(iter(gray), init[:4], method=method)
    error = np.linalg.norm(tracks.xy - truth[:6, :4], axis=2)
    assert tracks.xy.shape == (6, 4, 2)
    assert np.median(error[tracks.valid]) < 2.0


def test_point_leaving_the_frame_is_flagged_not_dropped():
    frames, transforms = moving_clip(24, size=(160, 120), seed=3, amplitude=0.0)
    # slide the clip left by 3 px per frame: a point near the left border leaves the frame;
    # what comes in on the right is black
    slid = np.stack([np.roll(f, -3 * t, axis=1) for t, f in enumerate(frames)])
    for t in range(1, 24):
        slid[t, :, 160 - 3 * t :] = 0
    init = np.array([[30.0, 60.0], [100.0, 60.0], [120.0, 40.0]])
    truth = apply(transforms, init) - np.array([3.0, 0.0]) * np.arange(24)[:, None, None]
    tracks = track_points(iter(slid), init, method="ncc")
    assert tracks.xy.shape == (24, 3, 2)
    gone = truth[:, 0, 0] < 7
    assert not tracks.valid[gone, 0].any()
    assert tracks.valid[~gone, 0].all()
    # carried along with the other points (held in place it would be up to 40 px off; measured
    # 1.23 px: with two points left, the neighbours' prior pulls each by ~0.25 px)
    assert np.linalg.norm(tracks.xy[gone, 0] - truth[gone, 0], axis=1).max() < 1.5
    assert tracks.valid[:, 2].all()
    assert np.linalg.norm(tracks.xy[:, 2] - truth[:, 2], axis=1).max() < 0.5


def test_occluded_point_is_flagged_and_recovered(clip):
    frames, init, truth = clip
    occluded = frames.copy()
    x, y = np.rint(truth[10:14, 0]).astype(int).T[0], np.rint(truth[10:14, 0]).astype(int).T[1]
    for k, t in enumerate(range(10, 14)):
        occluded[t, y[k] - 12 : y[k] + 13, x[k] - 12 : x[k] + 13] = 128
    tracks = track_points(iter(occluded), init, method="ncc")
    assert not tracks.valid[10:14, 0].any()
    assert tracks.valid[16:, 0].all()
    assert np.linalg.norm(tracks.xy[16:, 0] - truth[16:, 0], axis=1).max() < 0.5


def write_points(path, names, xy):
    path.write_text(json.dumps({"names": list(names), "xy": np.asarray(xy).tolist()}))
    return path


def tracked_setup(tmp_path, n_frames=12):
    layout = load_layout("zhang134")
    names = [layout.point_names[i] for i in layout.tracked]
    frames, transforms = moving_clip(n_frames, size=(160, 120), seed=4)
    rng = np.random.default_rng(5)
    init = rng.uniform([20, 20], [140, 100], (len(names), 2))
    return frames, transforms, names, init


def test_stage_streams_chunks_and_names_points(tmp_path):
    frames, transforms, names, init = tracked_setup(tmp_path)
    # shuffled order in the file: the output follows the layout's order
    order = np.random.default_rng(6).permutation(len(names))
    csv_path = tmp_path / "first.csv"
    csv_path.write_text("name,x,y\n" + "".join(f"{names[i]},{init[i, 0]},{init[i, 1]}\n" for i in order))
    stream = MemoryStream(frames, chunk=5)
    out = CorrelationTrack().run({"frames": stream, "init": csv_path}, {"layout": "zhang134"}, context(tmp_path))
    points = out["points"]
    assert stream.reads == 3
    assert list(points["names"]) == names
    assert points["xy"].dtype == np.float64 and points["valid"].dtype == bool
    assert tuple(points["size"]) == (160, 120) and float(points["fps"]) == 25.0
    error = np.linalg.norm(points["xy"] - apply(transforms, init), axis=2)
    assert np.median(error) < 0.3


def test_stage_reads_a_json_points_file(tmp_path):
    frames, _, names, init = tracked_setup(tmp_path, n_frames=3)
    path = write_points(tmp_path / "first_frame.json", names, init)
    out = CorrelationTrack().run({"frames": MemoryStream(frames), "init": path}, {}, context(tmp_path))
    np.testing.assert_array_equal(out["points"]["xy"][0], init)


@pytest.mark.parametrize(
    "problem, message",
    [
        ("missing", "not found"),
        ("count", "do not match"),
        ("names", "unknown"),
        ("outside", "outside"),
        ("garbled", "cannot read"),
    ],
)
def test_bad_first_frame_points(tmp_path, problem, message):
    frames, _, names, init = tracked_setup(tmp_path, n_frames=2)
    path = tmp_path / "first.json"
    if problem == "count":
        write_points(path, names[:-1], init[:-1])
    elif problem == "names":
        write_points(path, names[:-1] + ["nobody"], init)
    elif problem == "outside":
        init[3] = (170.0, 50.0)
        write_points(path, names, init)
    elif problem == "garbled":
        path.write_text("{not json")
    with pytest.raises(StageError, match=message) as info:
        CorrelationTrack().run({"frames": MemoryStream(frames), "init": path}, {}, context(tmp_path))
    assert "first.json" in str(info.value)


def test_read_first_frame_points_json_mapping(tmp_path):
    path = tmp_path / "p.json"
    path.write_text(json.dumps({"points": {"a": [1.5, 2.0], "b": [3.0, 4.25]}}))
    names, xy, frame_size = read_first_frame_points(path)
    assert names == ["a", "b"] and frame_size is None
    np.testing.assert_array_equal(xy, [[1.5, 2.0], [3.0, 4.25]])


def test_points_marked_on_another_frame_size_are_refused(tmp_path):
    frames, _, names, init = tracked_setup(tmp_path, n_frames=2)
    height, width = frames[0].shape[:2]
    path = tmp_path / "first.csv"
    rows = "\n".join(f"{n},{x},{y}" for n, (x, y) in zip(names, init))
    path.write_text(f"# frame_size: {width} {height}\nname,x,y\n{rows}\n")
    out = CorrelationTrack().run({"frames": MemoryStream(frames), "init": path}, {}, context(tmp_path))
    assert out["points"]["xy"].shape == (2, len(names), 2)
    path.write_text(f"# frame_size: {2 * width} {2 * height}\nname,x,y\n{rows}\n")
    with pytest.raises(StageError, match=f"marked on a {2 * width}x{2 * height} frame.*{width}x{height}"):
        CorrelationTrack().run({"frames": MemoryStream(frames), "init": path}, {}, context(tmp_path))


def test_a_folder_is_not_a_points_file(tmp_path):
    frames, _, names, init = tracked_setup(tmp_path, n_frames=2)
    write_points(tmp_path / "first.json", names, init)
    with pytest.raises(StageError, match="not found"):
        CorrelationTrack().run({"frames": MemoryStream(frames), "init": tmp_path}, {}, context(tmp_path))
