"""The report's series against ground truth and against the functions they stand for."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stages.geometry.signals import SIGNALS, expression_signals
from stages.report import series
from tests.stages.report.synthetic import level_neutral, mouth_opening, geometry


def test_signals_over_all_points_is_expression_signals():
    neutral, names, eye = level_neutral()
    xy = geometry(neutral, names, eye, mouth_opening(12, 0.3, 6)) + np.random.default_rng(1).normal(0, 1, (12, 1, 2))
    full = expression_signals(xy, names)
    over = series.signals_over(xy, names, series.shared_signal_points(names))
    for key in full:
        np.testing.assert_allclose(over[key], full[key], rtol=0, atol=1e-12)


def test_signals_over_a_subset_average_only_the_kept_points():
    neutral, names, eye = level_neutral()
    xy = np.repeat(neutral[None], 2, axis=0)
    xy[1, names.index("mouth_inner_7"), 1] += 0.25 * eye  # a kept lower-lip point
    xy[1, names.index("mouth_inner_8"), 1] += 9.0 * eye  # not kept: must not count
    keep = ("mouth_inner_2", "mouth_inner_7", "brow_l_0", "brow_r_0")
    subset = [i for i, n in enumerate(names) if n in keep or not n.startswith(("mouth_inner", "brow"))]
    values = series.signals_over(xy[:, subset], [names[i] for i in subset], keep)
    assert values["mouth_open"][1] - values["mouth_open"][0] == pytest.approx(0.25, abs=1e-12)
    assert series.shared_signal_points(names, [names[i] for i in subset]) == keep


def test_shared_signal_points_names_the_missing_group():
    neutral, names, _ = level_neutral()
    with pytest.raises(ValueError, match="mouth_inner_1"):
        series.shared_signal_points(names, [n for n in names if not n.startswith("mouth_inner")])


def test_head_pose_prefers_ypr_deg_and_derives_it_from_R():
    ypr = np.array([[10.0, -5.0, 3.0], [-30.0, 12.0, -7.0], [0.0, 0.0, 0.0]])
    R = Rotation.from_euler("YXZ", ypr, degrees=True).as_matrix()
    valid = np.array([True, True, False])
    derived = series.head_pose_series({"R": R, "valid": valid})
    np.testing.assert_allclose(np.stack([derived[k] for k in ("yaw", "pitch", "roll")], 1)[:2], ypr[:2], atol=1e-9)
    assert np.isnan(derived["yaw"][2])
    given = series.head_pose_series({"R": np.repeat(np.eye(3)[None], 3, 0), "ypr_deg": ypr, "valid": valid})
    assert given["pitch"][1] == 12.0


def test_dominant_examples_and_warp_only():
    coeff = np.array([[[0.2, 0.8, np.nan], [np.nan, np.nan, 1.0]], [[0.0, 0.0, np.nan], [np.nan, np.nan, 0.0]]])
    out = series.dominant_examples({"coeff": coeff, "subregions": np.array(["a", "b"]), "examples": np.array(["e0", "e1", "t0"])})
    np.testing.assert_array_equal(out["example"], [[1, 2], [-1, -1]])
    np.testing.assert_array_equal(out["weight"], [[0.8, 1.0], [0.0, 0.0]])


def test_peaks_spans_and_tracking():
    t = np.zeros(10)
    t[3], t[7] = 0.3, -0.1
    signals = {s: {"performer": t if s == "mouth_open" else np.zeros(10), "target": np.zeros(10)} for s in SIGNALS}
    assert series.peak_frames(signals) == [(3, "mouth open max"), (7, "mouth open min")]
    assert series.spans(np.array([1, 1, 0, 1, 0, 0, 1], bool)) == [(0, 1), (3, 3), (6, 6)]
    valid = np.array([[True, False], [False, False]])
    tracking = series.tracking_series({"valid": valid, "confidence": np.array([[0.5, 9.0], [1.0, 1.0]])})
    np.testing.assert_array_equal(tracking["valid_fraction"], [0.5, 0.0])
    assert tracking["mean_confidence"][0] == 0.5 and np.isnan(tracking["mean_confidence"][1])
