"""Gaussian trajectory smoothing against scipy and a direct evaluation of the normalized sum."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter1d

from runner.stage import StageError
from stages.geometry.smooth import GaussianSmooth, gaussian_smooth
from tests.stages.geometry.synthetic import context


def sample(values: np.ndarray, valid: np.ndarray, j: int, i: int) -> tuple[np.ndarray, bool]:
    """Point i at frame j, continued past the ends by odd reflection about the end sample."""
    last = len(values) - 1
    if 0 <= j <= last:
        return values[j, i], bool(valid[j, i])
    end, mirror = (0, -j) if j < 0 else (last, 2 * last - j)
    return 2 * values[end, i] - values[mirror, i], bool(valid[end, i] and valid[mirror, i])


def direct(values: np.ndarray, valid: np.ndarray, sigma: float, radius: int) -> np.ndarray:
    """The normalized, truncated, masked Gaussian sum evaluated term by term, (T, N, 2)."""
    out = np.empty_like(values)
    for t in range(len(values)):
        for i in range(values.shape[1]):
            total, weight = np.zeros(values.shape[2:]), 0.0
            for j in range(t - radius, t + radius + 1):
                x, ok = sample(values, valid, j, i)
                if ok:
                    w = np.exp(-0.5 * ((j - t) / sigma) ** 2)
                    total, weight = total + w * x, weight + w
            out[t, i] = total / weight if weight > 0 else values[t, i]
    return out


def test_interior_matches_scipy_gaussian_filter():
    rng = np.random.default_rng(0)
    values = rng.normal(size=(60, 3, 2))
    smoothed, valid = gaussian_smooth(values, sigma=2.0, truncate=4.0)
    reference = gaussian_filter1d(values, 2.0, axis=0, truncate=4.0)
    np.testing.assert_allclose(smoothed[8:-8], reference[8:-8], atol=1e-12)
    assert valid.shape == (60,) and valid.all()


def test_ends_and_masked_frames_match_the_direct_sum():
    rng = np.random.default_rng(1)
    values = rng.normal(size=(30, 4, 2))
    valid = rng.random((30, 4)) > 0.3
    values[~valid] = 1e6  # garbage in masked frames must not leak
    smoothed, out_valid = gaussian_smooth(values, valid, sigma=1.5, truncate=3.0)
    np.testing.assert_allclose(smoothed, direct(values, valid, 1.5, 5), atol=1e-9)
    assert (out_valid >= valid).all()


def test_constant_and_linear_trajectories():
    t = np.arange(40, dtype=np.float64)
    values = np.stack([np.full(40, 7.5), 0.4 * t + 2.0], axis=1)[:, None, :]
    valid = np.ones((40, 1), bool)
    valid[[0, 17, 18, 39]] = False
    smoothed, out_valid = gaussian_smooth(values, valid, sigma=2.0)
    np.testing.assert_allclose(smoothed[:, 0, 0], 7.5, atol=1e-12)  # constant everywhere, ends included
    symmetric = np.r_[7:11, 25:33]  # frames whose whole kernel (radius 6) is valid
    np.testing.assert_allclose(smoothed[symmetric, 0, 1], values[symmetric, 0, 1], atol=1e-9)
    assert out_valid[17, 0] and out_valid[18, 0]  # short gap filled
    assert out_valid[0, 0] and out_valid[39, 0]


def test_odd_reflection_keeps_the_end_samples_and_linear_motion():
    rng = np.random.default_rng(5)
    t = np.arange(30, dtype=np.float64)
    linear = np.stack([1.5 * t - 4.0, -0.7 * t + 30.0], axis=1)[:, None, :]
    smoothed, _ = gaussian_smooth(linear, np.ones((30, 1), bool), sigma=2.0)
    np.testing.assert_allclose(smoothed, linear, atol=1e-9)  # ends included
    noisy = linear + rng.normal(0, 0.5, linear.shape)
    valid = rng.random((30, 1)) > 0.2
    valid[[0, -1]] = True
    smoothed, _ = gaussian_smooth(noisy, valid, sigma=2.0)
    np.testing.assert_allclose(smoothed[[0, -1]], noisy[[0, -1]], atol=1e-9)  # the neutral frame stays put
    # a fast start: renormalizing the truncated kernel would pull the first frames towards later ones
    accelerating = (0.05 * t**2)[:, None, None] * np.ones((1, 1, 2))
    smoothed, _ = gaussian_smooth(accelerating, sigma=1.5)
    renormalized = np.sum([np.exp(-0.5 * (k / 1.5) ** 2) * accelerating[1 + k] for k in range(-1, 6)], axis=0)
    renormalized /= np.sum([np.exp(-0.5 * (k / 1.5) ** 2) for k in range(-1, 6)])
    assert smoothed[0] == pytest.approx(accelerating[0], abs=1e-12)
    assert np.abs(smoothed[1] - accelerating[1]).max() < np.abs(renormalized - accelerating[1]).max()


def test_long_gap_stays_invalid_and_noise_is_reduced():
    rng = np.random.default_rng(2)
    truth = np.sin(np.arange(100) / 10.0)[:, None, None] * np.ones((1, 1, 2))
    noisy = truth + rng.normal(0, 0.1, truth.shape)
    valid = np.ones((100, 1), bool)
    valid[40:60] = False
    smoothed, out_valid = gaussian_smooth(noisy, valid, sigma=2.0)
    assert not out_valid[47:53, 0].any()
    keep = valid[:, 0]
    assert np.abs(smoothed - truth)[keep].mean() < 0.5 * np.abs(noisy - truth)[keep].mean()


def test_sigma_zero_is_identity():
    values = np.random.default_rng(3).normal(size=(10, 2, 2))
    smoothed, _ = gaussian_smooth(values, np.ones((10, 2), bool), sigma=0.0)
    np.testing.assert_array_equal(smoothed, values)


def test_stage_keeps_bundle_keys(tmp_path):
    rng = np.random.default_rng(4)
    bundle = {"xy": rng.normal(size=(20, 3, 2)), "valid": np.ones((20, 3), bool),
              "names": np.array(["a", "b", "c"]), "confidence": np.ones((20, 3), np.float32)}
    out = GaussianSmooth().run({"points": bundle}, {"sigma": 1.0}, context(tmp_path))["points"]
    assert set(out) == set(bundle) and out["xy"].shape == (20, 3, 2)
    np.testing.assert_allclose(out["xy"], direct(bundle["xy"], bundle["valid"], 1.0, 3), atol=1e-9)
    with pytest.raises(StageError, match="sigma"):
        GaussianSmooth().run({"points": bundle}, {"sigma": -1.0}, context(tmp_path))


def test_nan_in_an_invalid_sample_does_not_spread():
    rng = np.random.default_rng(3)
    values = rng.normal(size=(30, 2))
    valid = np.ones(30, bool)
    valid[12] = False
    clean, _ = gaussian_smooth(values, valid, sigma=2.0)
    values[12] = np.nan
    with_nan, valid_out = gaussian_smooth(values, valid, sigma=2.0)
    np.testing.assert_array_equal(with_nan, clean)
    assert np.isfinite(with_nan).all() and valid_out.all()
