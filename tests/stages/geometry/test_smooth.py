"""Trajectory smoothing: the Gaussian against scipy and a direct evaluation of the normalized sum; the
One Euro filter against a scalar reference and on synthetic openings with known truth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import convolve1d, gaussian_filter1d

from runner.stage import StageError
from scripts.bench_smoothing import jitter, opening_face, retention
from stages.geometry.smooth import (
    GaussianSmooth,
    OneEuroSmooth,
    convolve_time,
    face_translation,
    gaussian_kernel,
    gaussian_smooth,
    one_euro_smooth,
    one_euro_smooth_face,
)
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
    bundle = {
        "xy": rng.normal(size=(20, 3, 2)),
        "valid": np.ones((20, 3), bool),
        "names": np.array(["a", "b", "c"]),
        "confidence": np.ones((20, 3), np.float32),
    }
    out = GaussianSmooth().run({"points": bundle}, {"sigma": 1.0}, context(tmp_path))["points"]
    assert set(out) == set(bundle) and out["xy"].shape == (20, 3, 2)
    np.testing.assert_allclose(out["xy"], direct(bundle["xy"], bundle["valid"], 1.0, 3), atol=1e-9)
    with pytest.raises(StageError, match="sigma"):
        GaussianSmooth().run({"points": bundle}, {"sigma": -1.0}, context(tmp_path))
    sigma = next(p for p in GaussianSmooth.params if p.name == "sigma")
    assert "out of range" in sigma.problem(-1.0) and sigma.problem(0.0) is None  # refused when the graph loads


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


class ReferenceOneEuro:
    """The One Euro filter as Casiez et al.'s pseudo-code has it: one scalar, timestamped samples."""

    def __init__(self, min_cutoff: float, beta: float, d_cutoff: float):
        self.min_cutoff, self.beta, self.d_cutoff = min_cutoff, beta, d_cutoff
        self.x_prev = self.dx_prev = self.t_prev = None

    @staticmethod
    def alpha(te: float, cutoff: float) -> float:
        tau = 1.0 / (2 * np.pi * cutoff)
        return 1.0 / (1.0 + tau / te)

    def __call__(self, x: float, t: float) -> float:
        if self.x_prev is None:
            self.x_prev, self.dx_prev, self.t_prev = x, 0.0, t
            return x
        te = t - self.t_prev
        dx = (x - self.x_prev) / te
        self.dx_prev = self.dx_prev + self.alpha(te, self.d_cutoff) * (dx - self.dx_prev)
        cutoff = self.min_cutoff + self.beta * abs(self.dx_prev)
        self.x_prev = self.x_prev + self.alpha(te, cutoff) * (x - self.x_prev)
        self.t_prev = t
        return self.x_prev


def reference_one_euro(x: np.ndarray, ok: np.ndarray, fps: float, options: dict) -> np.ndarray:
    """One trajectory ``(T,)``: odd reflection, the reference filter forward over the valid samples
    (timestamps frame / fps), backward over its output, linear interpolation over invalid frames."""
    pad = min(int(np.ceil(5 * fps / (2 * np.pi * options["min_cutoff"]))), len(x) - 1)
    ext = np.array([sample(x[:, None], ok[:, None], j, 0)[0] for j in range(-pad, len(x) + pad)])
    ext_ok = np.array([sample(x[:, None], ok[:, None], j, 0)[1] for j in range(-pad, len(x) + pad)])
    frames = np.flatnonzero(ext_ok)
    forward = ReferenceOneEuro(**options)
    once = [forward(ext[j], j / fps) for j in frames]
    backward = ReferenceOneEuro(**options)
    twice = [backward(v, -j / fps) for j, v in zip(frames[::-1], once[::-1])][::-1]
    inside = (frames >= pad) & (frames < pad + len(x))
    return np.interp(np.arange(len(x)), frames[inside] - pad, np.array(twice)[inside])


def test_one_euro_matches_a_scalar_reference_with_gaps():
    rng = np.random.default_rng(6)
    values = np.cumsum(rng.normal(0, 2.0, (80, 3, 2)), axis=0)
    valid = rng.random((80, 3)) > 0.25
    valid[0, 0] = False  # the first frame invalid: its reflection is too
    values[~valid] = np.nan
    options = {"min_cutoff": 0.8, "beta": 0.3, "d_cutoff": 2.0}
    smoothed, valid_out = one_euro_smooth(values, valid, fps=25.0, **options)
    np.testing.assert_array_equal(valid_out, valid)
    for i in range(3):
        for c in range(2):
            expected = reference_one_euro(values[:, i, c], valid[:, i], 25.0, options)
            np.testing.assert_allclose(smoothed[:, i, c], expected, atol=1e-9)


def test_one_euro_keeps_short_openings_and_removes_jitter():
    """A face whose mouth points open for 3-5 frames by 10-40 px on slow head motion, 0.3 and 1 px
    white noise: the stage defaults keep >= 95% of the amplitude (the Gaussian of sigma 1.5 keeps
    64-82%), and the jitter and the error against the truth fall below the raw samples'."""
    clip = opening_face(24, 400, fps=30.0, seed=3)
    hardest = opening_face(24, 400, fps=30.0, seed=4, amplitude_px=(10.0, 10.0))
    defaults = {p.name: p.default for p in OneEuroSmooth.params if p.name != "fps"}
    every = np.ones((400, 24), bool)
    rng = np.random.default_rng(7)
    for noise in (0.3, 1.0):
        noisy = clip["truth"] + rng.normal(0, noise, clip["truth"].shape)
        smoothed, _ = one_euro_smooth_face(noisy, every, fps=30.0, **defaults)
        for width in (3, 4, 5):
            assert retention(smoothed, clip, width) >= 0.95
        small = one_euro_smooth_face(
            hardest["truth"] + rng.normal(0, noise, hardest["truth"].shape), every, fps=30.0, **defaults
        )[0]
        assert retention(small, hardest, 3) >= 0.95
        gaussian = gaussian_smooth(noisy, sigma=1.5)[0]
        assert retention(gaussian, clip, 3) < 0.8  # what the Gaussian loses on the same openings
        assert jitter(smoothed, clip["quiet"]) < 0.5 * jitter(noisy, clip["quiet"])
        assert np.sqrt(np.mean((smoothed - clip["truth"]) ** 2)) < np.sqrt(np.mean((noisy - clip["truth"]) ** 2))


def test_one_euro_constant_ends_and_still_points():
    t = np.arange(60, dtype=np.float64)
    constant = np.full((60, 1, 2), 12.25)
    np.testing.assert_allclose(one_euro_smooth(constant, fps=30.0)[0], constant, atol=1e-12)
    rng = np.random.default_rng(8)
    still = 5.0 + rng.normal(0, 0.5, (200, 4, 2))
    smoothed, _ = one_euro_smooth(still, fps=30.0)
    # noise raises the speed estimate and with it the cutoff: at rest the One Euro filter trades
    # some of its smoothing for keeping short openings (measured: error x0.72, jitter x0.33)
    assert np.abs(smoothed - 5.0)[10:-10].mean() < 0.8 * np.abs(still - 5.0)[10:-10].mean()
    quiet = np.ones(200, bool)
    assert jitter(smoothed, quiet) < 0.5 * jitter(still, quiet)
    # a steady motion near the ends is not pulled towards the clip's inside (odd reflection)
    linear = np.stack([2.0 * t, -t], axis=1)[:, None, :]
    ends = one_euro_smooth(linear, fps=30.0)[0][[0, -1]]
    np.testing.assert_allclose(ends, linear[[0, -1]], atol=0.05)


def test_one_euro_invalid_samples_are_interpolated_and_stay_flagged():
    rng = np.random.default_rng(9)
    values = rng.normal(0, 1.0, (40, 2))
    valid = np.ones(40, bool)
    valid[[5, 20, 21, 22]] = False
    clean, _ = one_euro_smooth(values, valid, fps=30.0)
    values[valid == 0] = np.nan
    smoothed, valid_out = one_euro_smooth(values, valid, fps=30.0)
    np.testing.assert_array_equal(smoothed, clean)
    np.testing.assert_array_equal(valid_out, valid)
    np.testing.assert_allclose(smoothed[21], smoothed[19] + (smoothed[23] - smoothed[19]) * 2 / 4, atol=1e-12)
    never = np.full((10, 1), 3.0)
    out, out_valid = one_euro_smooth(never, np.zeros(10, bool), fps=30.0)
    np.testing.assert_array_equal(out, never)
    assert not out_valid.any()


def test_one_euro_stage_takes_the_bundle_fps(tmp_path):
    rng = np.random.default_rng(10)
    bundle = {
        "xy": np.cumsum(rng.normal(size=(30, 3, 2)), axis=0),
        "valid": np.ones((30, 3), bool),
        "names": np.array(["a", "b", "c"]),
        "fps": np.array(25.0),
    }
    out = OneEuroSmooth().run({"points": bundle}, {}, context(tmp_path))["points"]
    assert set(out) == set(bundle)
    np.testing.assert_allclose(out["xy"], one_euro_smooth_face(bundle["xy"], bundle["valid"], fps=25.0)[0], atol=1e-12)
    del bundle["fps"]
    out = OneEuroSmooth().run({"points": bundle}, {"fps": 50.0}, context(tmp_path))["points"]
    np.testing.assert_allclose(out["xy"], one_euro_smooth_face(bundle["xy"], bundle["valid"], fps=50.0)[0], atol=1e-12)
    with pytest.raises(StageError, match="smooth.one_euro: min_cutoff must be > 0"):
        OneEuroSmooth().run({"points": bundle}, {"min_cutoff": 0.0}, context(tmp_path))


def test_face_translation_of_a_rigid_face_with_dropouts():
    rng = np.random.default_rng(11)
    shape = rng.uniform(0, 100, (6, 2))
    motion = np.cumsum(rng.normal(0, 3.0, (25, 2)), axis=0)
    motion -= motion[0]
    xy = shape[None] + motion[:, None]
    valid = rng.random((25, 6)) > 0.3
    valid[:, 0] = True  # at least one point in common between neighbouring frames
    xy[~valid] = np.nan
    np.testing.assert_allclose(face_translation(xy, valid)[:, 0], motion, atol=1e-9)


def test_one_euro_in_the_face_frame_smooths_a_still_face_on_a_moving_head():
    """A rigid face moving fast (head motion) with 0.5 px landmark noise: in the face's frame the
    filter sees still points and smooths them hard; on the image positions the head's speed keeps
    the cutoff up. Mouth openings pass in both (test above)."""
    rng = np.random.default_rng(12)
    t = np.arange(150, dtype=np.float64)
    head = np.stack([40 * np.sin(t / 8.0), 25 * np.cos(t / 11.0)], axis=1)
    truth = rng.uniform(0, 100, (20, 2))[None] + head[:, None]
    noisy = truth + rng.normal(0, 0.5, truth.shape)
    every = np.ones((150, 20), bool)
    in_face = one_euro_smooth_face(noisy, every, fps=30.0)[0]
    in_image = one_euro_smooth(noisy, every, fps=30.0)[0]

    def error(xy: np.ndarray) -> float:
        return float(np.abs(xy - truth)[5:-5].mean())

    def shake(xy: np.ndarray) -> float:  # mean |second difference| of the error, px
        return float(np.abs(np.diff(xy - truth, n=2, axis=0)).mean())

    # measured: error 0.29 / 0.37 / 0.40 px, shake 0.39 / 0.80 / 0.96 px (face / image / raw)
    assert error(in_face) < 0.85 * error(in_image) and shake(in_face) < 0.6 * shake(in_image)
    with pytest.raises(ValueError, match=r"a mask \(T, N\)"):
        one_euro_smooth_face(noisy, every[:, :3], fps=30.0)


def test_time_convolution_matches_scipy_convolve1d():
    """convolve_time against scipy.ndimage.convolve1d (zero padding), short and long kernels."""
    values = np.random.default_rng(7).normal(size=(40, 5, 2))
    for sigma in (0.5, 1.5, 8.0):
        kernel = gaussian_kernel(sigma, truncate=3.0)
        np.testing.assert_allclose(
            convolve_time(values, kernel), convolve1d(values, kernel, axis=0, mode="constant", cval=0.0), rtol=0, atol=1e-12
        )
