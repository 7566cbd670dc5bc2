"""The clip's appearance model of a region (``stages.occlusion.model``) on synthetic strips whose
occluded frames are known."""

import numpy as np

from stages.occlusion import model

K, M, C, SHIFT = 16, 7, 2, 2


def synthetic_clip(frames: int, occluded: np.ndarray, seed: int = 0) -> np.ndarray:
    """Strips ``(F, K, M + 2 SHIFT, C)``: the region's structure (a fixed random pattern at a
    strength of 0.7-1.3, displaced by up to one sample along the normals, plus noise) where
    ``occluded`` is False; a smooth shaded surface (a gentle ramp, plus the same noise) where True."""
    rng = np.random.default_rng(seed)
    pattern = rng.normal(0, 0.2, (K, M + 2 * SHIFT + 2, C))
    u = np.linspace(-1, 1, M + 2 * SHIFT)[None, :, None]
    strips = np.empty((frames, K, M + 2 * SHIFT, C))
    for f in range(frames):
        if occluded[f]:
            strips[f] = rng.uniform(-0.05, 0.05) * u + rng.uniform(-0.05, 0.05, (K, 1, C))
        else:
            shift = rng.integers(0, 3)
            strips[f] = rng.uniform(0.7, 1.3) * pattern[:, shift : shift + M + 2 * SHIFT]
        strips[f] += rng.normal(0, 0.02, strips[f].shape)
    return strips


def test_a_clip_occluded_from_its_start_for_most_of_it_is_judged_from_its_face_frames():
    frames = 100
    occluded = np.arange(frames) < 60
    win = model.windows(synthetic_clip(frames, occluded), SHIFT)
    assert win.shape == (frames, 2 * SHIFT + 1, K * M * C)
    np.testing.assert_allclose(win.mean(axis=2), 0.0, atol=1e-12)
    template, seen = model.template(win, positions=K, keep=0.5)
    np.testing.assert_array_equal(seen, ~occluded)
    visible = model.visibility(win, template, seen)
    assert np.median(visible[~occluded]) == np.median(visible[seen])
    assert visible[~occluded].min() > 0.6 and np.abs(visible[occluded]).max() < 0.2


def test_relative_is_zero_for_a_structure_the_clip_never_shows():
    seen = np.ones(4, bool)
    np.testing.assert_allclose(model.relative(np.array([2.0, 4.0, 4.0, 6.0]), seen), [0.5, 1.0, 1.0, 1.5])
    np.testing.assert_array_equal(model.relative(np.array([-1.0, 0.0, -2.0, 0.0]), seen), np.zeros(4))


def test_median_filter_removes_short_dips_and_keeps_longer_ones():
    values = np.ones(20)
    values[5:7] = 0.0  # two frames
    values[10:13] = 0.0  # three frames
    values[0] = 0.0  # at the start
    filtered = model.median_filter(values, 5)
    np.testing.assert_array_equal(filtered[:9], 1.0)
    np.testing.assert_array_equal(filtered[10:13], 0.0)
    np.testing.assert_array_equal(filtered[14:], 1.0)
    np.testing.assert_array_equal(model.median_filter(values, 1), values)


def test_a_face_far_from_its_typical_shape_is_judged_against_frames_like_it():
    """The region's look changes with the face's shape (a head turning away over the clip:
    pattern A at shape 0 becomes pattern B at shape 1); a hand hides it in frames 40-59. The
    typical template alone loses the turned frames; against the seen frames nearest in shape
    they are seen, and the hand is not."""
    rng = np.random.default_rng(1)
    frames = 100
    a, b = rng.normal(0, 0.2, (2, K, M + 2 * SHIFT, C))
    s = np.linspace(0, 1, frames) ** 2  # most frames near the typical shape
    occluded = (np.arange(frames) >= 40) & (np.arange(frames) < 60)
    strips = (1 - s)[:, None, None, None] * a + s[:, None, None, None] * b
    strips[occluded] = rng.uniform(-0.05, 0.05, (occluded.sum(), K, 1, C))
    strips += rng.normal(0, 0.02, strips.shape)
    win = model.windows(strips, SHIFT)
    template, seen = model.template(win, positions=K, keep=0.5)
    typical = model.visibility(win, template, seen)
    assert typical[-5:].max() < 0.3  # the turned face against the typical one
    suspect = np.flatnonzero(typical < 0.5)
    local = model.local_visibility(win, s[:, None], seen, suspect, neighbours=5)
    judged = typical.copy()
    judged[suspect] = np.maximum(typical[suspect], local)
    assert judged[~occluded].min() > 0.5
    assert np.abs(judged[occluded]).max() < 0.2


def test_a_structured_occluder_for_half_the_clip_is_not_taken_for_the_region():
    """Fingers across a brow: dark gaps running across the contour, more contrast than the
    region's own structure, in the first half of the clip. The model starts from the frames with
    the most structure *across* the contour (the profile averaged along it), so from the face."""
    rng = np.random.default_rng(2)
    frames = 80
    occluded = np.arange(frames) < 40
    strips = synthetic_clip(frames, np.zeros(frames, bool), seed=2)
    gaps = np.where(np.arange(K) % 4 == 0, -0.6, 0.1)[:, None, None]  # constant across, varying along
    strips[occluded] = gaps + rng.normal(0, 0.02, (occluded.sum(), K, M + 2 * SHIFT, C))
    win = model.windows(strips, SHIFT)
    energy = np.einsum("fsd,fsd->f", win[:, SHIFT : SHIFT + 1], win[:, SHIFT : SHIFT + 1])
    assert energy[occluded].min() > energy[~occluded].max()  # the occluder has more structure
    template, seen = model.template(win, positions=K, keep=0.5)
    np.testing.assert_array_equal(seen, ~occluded)
    visible = model.visibility(win, template, seen)
    assert visible[~occluded].min() > 0.6 and np.abs(visible[occluded]).max() < 0.2
