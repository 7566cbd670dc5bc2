import numpy as np
import pytest

from stages.eigen.patches import cut_patches, feature_windows, luminance
from tests.stages.eigen import scene

IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def similarity(scale, angle_deg, tx, ty):
    a = scale * np.cos(np.radians(angle_deg))
    b = scale * np.sin(np.radians(angle_deg))
    return np.array([a, b, tx, ty])


def test_windows_cover_their_points_with_margin():
    windows = scene.windows()
    assert [w.name for w in windows] == ["a", "b"]
    for w in windows:
        grid = w.grid()
        assert grid.shape == (*w.shape, 2) and grid.dtype == np.float64
        pts = scene.NEUTRAL[list(w.points)]
        assert np.all(pts >= grid[0, 0]) and np.all(pts <= grid[-1, -1])


def test_patches_are_invariant_to_a_known_similarity():
    params = np.array([0.8, 0.0, 0.3, 1.0])
    windows = scene.windows()
    reference, ok0 = cut_patches(scene.scene(params, IDENTITY), IDENTITY, windows)
    T = similarity(1.2, 14.0, 8.0, -6.0)
    moved_image = scene.scene(params, T, size=(220, 170))
    moved, ok1 = cut_patches(moved_image, T, windows)
    unnormalized, _ = cut_patches(moved_image, IDENTITY, windows)
    assert ok0.all() and ok1.all()
    for r, m, u in zip(reference, moved, unnormalized):
        assert r.dtype == np.float32 and r.shape == m.shape
        err = np.abs(r - m).mean()
        assert err < 0.01  # interpolation and 8-bit rounding only
        assert np.abs(r - u).mean() > 5 * err


def test_patches_normalize_a_rendered_head_moved_in_the_image():
    from scripts.make_fixtures import render_identity

    near = render_identity(1, {"smile": 0.5})
    moved = render_identity(1, {"smile": 0.5}, translation=(14.0, -9.0, 40.0))
    from stages.layout import load_layout
    from stages.geometry.compensate import fit_similarity

    layout = load_layout("zhang134")
    rigid = list(layout.rigid)
    windows = feature_windows(near["points"], layout.point_names)
    T = fit_similarity(near["points"][rigid], moved["points"][rigid])
    ref, _ = cut_patches(near["image"], IDENTITY, windows)
    got, ok = cut_patches(moved["image"], T, windows)
    raw, _ = cut_patches(moved["image"], IDENTITY, windows)
    assert ok.all()
    for r, g, u in zip(ref, got, raw):
        assert np.abs(r - g).mean() < 0.35 * np.abs(r - u).mean()


def test_a_feature_outside_the_image_is_masked_not_a_crash():
    windows = scene.windows()
    T = np.array([1.0, 0.0, 70.0, 0.0])  # feature b (x 80..120 in the neutral) leaves the 160 px wide image
    patches, ok = cut_patches(scene.scene(np.zeros(4), T), T, windows)
    assert ok.tolist() == [True, False]
    assert patches[1].shape == windows[1].shape and not patches[1].any()


def test_luminance_and_window_contracts():
    with pytest.raises(TypeError, match="uint8"):
        luminance(np.zeros((4, 4, 3), np.float32))
    with pytest.raises(ValueError, match="neutral points"):
        feature_windows(np.zeros((3, 2)), scene.NAMES)
