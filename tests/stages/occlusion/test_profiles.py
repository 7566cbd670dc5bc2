"""The strips across the regions' contours (``stages.occlusion.profiles``): where they sample and
what their channels measure."""

import numpy as np

from stages.occlusion import profiles
from stages.occlusion.profiles import PROFILES, SHIFT, make_sampler, sample_frame, sample_grid

EYE_PX = 100.0


def circle_points(order: int) -> tuple[list[str], np.ndarray]:
    """The mouth's outer lip line as a circle of radius 30 px about (200, 150), traversed one way
    or the other, with the outer eye corners ``EYE_PX`` apart."""
    angles = order * np.linspace(0, 2 * np.pi, 16, endpoint=False)
    lips = np.stack([200 + 30 * np.cos(angles), 150 + 30 * np.sin(angles)], axis=1)
    names = [f"mouth_outer_{k}" for k in range(16)] + ["eye_l_6", "eye_r_6", "eye_l_0", "eye_r_0", "nose_tip"]
    return names, np.vstack([lips, [[150.0, 60.0], [150.0 + EYE_PX, 60.0], [180, 60], [220, 60], [200, 100]]])


def test_closed_contour_normals_point_outwards_whichever_way_it_is_traversed():
    for order in (1, -1):
        names, xy = circle_points(order)
        sampler = make_sampler(names, xy[None], np.array([True]), ["mouth"])
        grid, eye = sample_grid(sampler, xy)
        assert eye == EYE_PX
        K, M = sampler.shapes["mouth"]
        radius = np.hypot(*(grid.reshape(K, M, 2) - [200, 150]).transpose(2, 0, 1))
        # the lip line resampled on the 16-gon: its radius varies by 30 (1 - cos(pi/16)) = 0.6 px
        expected = 30 + PROFILES["mouth"].offsets * EYE_PX
        np.testing.assert_allclose(radius, np.broadcast_to(expected, (K, M)), atol=0.8)
        assert M == PROFILES["mouth"].count + 2 * SHIFT


def test_a_collapsed_outline_keeps_the_clips_outward_side():
    """A shut eye's outline collapses to a line: its normals keep the side the open outline had."""
    names = [f"eye_l_{k}" for k in range(12)] + ["eye_r_6", "eye_r_0", "nose_tip"]
    t = np.linspace(0, np.pi, 7)
    upper = np.stack([100 + 20 * np.cos(t), 100 - 8 * np.sin(t)], axis=1)  # eye_l_0 inner corner (right) .. 6
    lower = np.stack([100 - 20 * np.cos(t[1:-1]), 100 + 8 * np.sin(t[1:-1])], axis=1)  # 7..11 back to the inner
    open_eye = np.vstack([upper, lower, [[300.0, 100.0], [160.0, 100.0], [130.0, 140.0]]])
    shut = open_eye.copy()
    shut[:12, 1] = 100.0
    sampler = make_sampler(names, np.stack([open_eye, open_eye, shut]), np.ones(3, bool), ["eye_l"])
    K, M = sampler.shapes["eye_l"]
    for xy in (open_eye, shut):
        grid = sample_grid(sampler, xy)[0].reshape(K, M, 2)
        outer = grid[:, -1] - grid[:, SHIFT]  # from the contour outwards
        top = grid[:, SHIFT, 1] < 100 - 1e-6 if xy is open_eye else np.arange(K) < K // 2
        assert (outer[top, 1] < 0).all() and (outer[~top, 1] > 0).all()


def test_sampling_reads_the_image_at_the_grid_at_the_face_scale():
    """A horizontal ramp is read back at the grid's x; a large face is reduced so the eye distance
    spans ``EYE_DISTANCE_PX`` first (area averaging keeps the ramp's values)."""
    ramp = np.tile(np.arange(640, dtype=np.float64)[None, :, None] * 0.25, (480, 1, 3)).astype(np.uint8)
    grid = np.array([[100.0, 200.0], [300.5, 220.0], [401.0, 100.0]])
    for eye in (60.0, 400.0):
        rgb = sample_frame(ramp, grid, eye)
        assert rgb.shape == (3, 3) and rgb.dtype == np.float32
        np.testing.assert_allclose(rgb[:, 0], np.floor(grid[:, 0] * 0.25), atol=1.0)


def test_channels_cancel_the_lights_level_and_colour():
    rng = np.random.default_rng(0)
    rgb = rng.uniform(60, 200, (3, 16, 9, 3))
    ch = profiles.channels(rgb)
    assert ch.shape == (3, 16, 9, 2)
    np.testing.assert_allclose(ch.mean(axis=(1, 2)), 0.0, atol=1e-6)
    brighter = profiles.channels(rgb * 1.6)
    np.testing.assert_allclose(brighter[..., 0], ch[..., 0], atol=1e-5)
    np.testing.assert_allclose(brighter[..., 1], ch[..., 1], atol=0.03)  # the +8 of the log ratio
    warmer = profiles.channels(rgb * [1.3, 1.0, 0.8])
    np.testing.assert_allclose(warmer[..., 1], ch[..., 1], atol=0.03)


def test_redness_contrast_is_positive_for_red_lips_inside_skin():
    profile = PROFILES["mouth"]
    offsets = profile.offsets
    rgb = np.where((offsets < 0)[None, None, :, None], [170.0, 80.0, 80.0], [200.0, 150.0, 120.0])
    strips = profiles.channels(np.broadcast_to(rgb, (2, 16, len(offsets), 3)))
    contrast = profiles.redness_contrast(strips, profile)
    assert (contrast > 0.3).all()
    flat = profiles.channels(np.full((1, 16, len(offsets), 3), 150.0))
    assert abs(profiles.redness_contrast(flat, profile)[0]) < 1e-6


def test_face_shape_does_not_change_with_the_faces_place_size_and_roll():
    names, xy = circle_points(1)
    sampler = make_sampler(names, xy[None], np.array([True]), ["mouth"])
    angle = np.radians(25.0)
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    moved = 1.7 * xy @ rot.T + [40.0, -12.0]
    np.testing.assert_allclose(profiles.shape(sampler, moved[None], 0), profiles.shape(sampler, xy[None], 0), atol=1e-12)
    smiled = xy.copy()
    smiled[:16, 0] *= 1.1  # a wider mouth is another shape
    assert np.abs(profiles.shape(sampler, smiled[None], 0) - profiles.shape(sampler, xy[None], 0)).max() > 0.1
