"""``bench.py seen`` (scripts/bench_seen.py): the blendshape measures of a result against the
performer's, on scores whose answer is known by construction, and Pearson r against scipy's."""

from __future__ import annotations

import numpy as np
from scipy.stats import pearsonr

from scripts.bench_seen import PEAK, SEEN_STATES, aggregate, seen_measures
from stages.landmarks.landmarker import BLENDSHAPE_NAMES

T = 120


def scores(brow: np.ndarray, jaw: np.ndarray) -> np.ndarray:
    """``(T, 52)`` blendshape scores: both brow-down categories ``brow``, ``jawOpen`` ``jaw``, the rest 0."""
    out = np.zeros((len(brow), len(BLENDSHAPE_NAMES)))
    out[:, BLENDSHAPE_NAMES.index("browDownLeft")] = brow
    out[:, BLENDSHAPE_NAMES.index("browDownRight")] = brow
    out[:, BLENDSHAPE_NAMES.index("jawOpen")] = jaw
    return out


def test_a_result_showing_half_the_performers_rise_gives_a_peak_ratio_of_one_half():
    rng = np.random.default_rng(0)
    t = np.arange(T)
    frown = 0.05 + 0.85 * np.clip(np.sin(2 * np.pi * t / 40), 0, None)  # a resting 0.05, peaks at 0.9
    jaw = rng.uniform(0, 0.4, T)  # never reaches PEAK
    performer = scores(frown, jaw)
    baseline = 0.2  # the target's resting face reads as a little frown
    result = scores(baseline + 0.5 * (frown - np.median(frown)), rng.uniform(0, 0.4, T))
    valid = np.ones(T, bool)
    m = seen_measures(performer, result, valid)
    peak = frown >= PEAK
    assert m["brow_down_peak_frames"] == 2 * peak.sum()  # two categories pooled
    assert np.isclose(m["brow_down_peak_ratio"], 0.5)
    assert np.isclose(m["brow_down_r"], 1.0)
    assert np.isnan(m["jaw_open_peak_ratio"]) and m["jaw_open_peak_frames"] == 0  # never at its peak
    assert np.isclose(m["jaw_open_r"], pearsonr(jaw, result[:, BLENDSHAPE_NAMES.index("jawOpen")])[0])
    assert set(m) == {f"{s}_{k}" for s in SEEN_STATES for k in ("r", "peak_frames", "peak_ratio")}


def test_frames_without_a_face_are_left_out():
    frown = np.tile([0.0, 0.9], T // 2)
    performer = scores(frown, np.zeros(T))
    result = scores(frown, np.zeros(T))
    result[::3] = 0.0  # the landmarker found no face there: its scores are zeros
    valid = np.ones(T, bool)
    valid[::3] = False
    assert np.isclose(seen_measures(performer, result, valid)["brow_down_peak_ratio"], 1.0)
    assert not np.isclose(seen_measures(performer, result, np.ones(T, bool))["brow_down_peak_ratio"], 1.0)


def test_aggregates_take_the_worst_and_the_median_over_the_runs_that_define_them():
    runs = {
        "a_onto_x": {"brow_down_peak_ratio": 0.2, "brow_down_r": 0.9},
        "b_onto_x": {"brow_down_peak_ratio": 0.6, "brow_down_r": 0.5},
        "c_onto_x": {"brow_down_peak_ratio": float("nan"), "brow_down_r": 0.7},
    }
    rows = {r["metric"]: r["value"] for r in aggregate(runs)}
    assert rows == {
        "seen_brow_down_peak_ratio_min": 0.2,
        "seen_brow_down_peak_ratio_median": 0.4,
        "seen_brow_down_r_median": 0.7,
    }
