"""The neutral estimated from a whole clip (stages.geometry.neutral) and occluded regions held
(stages.geometry.rigid3d.hold_occluded), against clips whose neutral is known."""

from __future__ import annotations

import numpy as np

from stages.geometry.neutral import REGIONS, estimate_neutral, point_regions
from stages.geometry.rigid3d import hold_occluded
from stages.landmarks.landmarker import BLENDSHAPE_NAMES
from stages.layout import load_layout
from tests.stages.geometry.test_mapping import eyed_face


def clip_without_a_neutral_start(layout, n_frames: int = 120, seed: int = 5):
    """A clip whose first 60 frames have the eyes shut and the brows down (crying), whose mouth is
    open in frames 30-80 and again in 100-110, with 0.3 px of landmark noise; the neutral (the
    truth) is never held by the first 30 frames. Blendshape scores follow each region's state."""
    rng = np.random.default_rng(seed)
    neutral = eyed_face(layout, eye_gap=12.0)
    names = layout.point_names
    upper = [layout.index(f"eye_{s}_{k}") for s in "lr" for k in range(1, 6)]
    brows = [i for i, n in enumerate(names) if n.startswith("brow_")]
    lower_lip = [layout.index(f"mouth_inner_{k}") for k in range(6, 10)] + [layout.index("chin")]
    xy = np.repeat(neutral[None], n_frames, axis=0)
    shapes = np.zeros((n_frames, len(BLENDSHAPE_NAMES)), np.float32)
    column = {n: i for i, n in enumerate(BLENDSHAPE_NAMES)}
    crying = np.arange(n_frames) < 60
    xy[crying][:, upper] += 0.0
    xy[np.ix_(crying, upper, [1])] += 11.0
    xy[np.ix_(crying, brows, [1])] += 6.0
    for name in ("eyeBlinkLeft", "eyeBlinkRight", "browDownLeft", "browDownRight"):
        shapes[crying, column[name]] = 0.8
    mouth = ((np.arange(n_frames) >= 30) & (np.arange(n_frames) < 80)) | (
        (np.arange(n_frames) >= 100) & (np.arange(n_frames) < 110)
    )
    xy[np.ix_(mouth, lower_lip, [1])] += 25.0
    shapes[mouth, column["jawOpen"]] = 0.7
    return neutral, xy + rng.normal(0, 0.3, xy.shape), shapes


def test_the_neutral_of_a_clip_that_starts_mid_expression_is_its_true_neutral():
    """Every region's neutral comes from frames where it rests: the eyes and brows from frames
    60+, the mouth from outside both openings; each within the noise of the truth, where the
    clip's first frame is 11 px off at the lids."""
    layout = load_layout("zhang134")
    neutral, xy, shapes = clip_without_a_neutral_start(layout)
    estimate = estimate_neutral(xy, layout.point_names, np.ones(len(xy), bool), shapes, BLENDSHAPE_NAMES)
    assert np.abs(estimate.neutral - neutral).max() < 0.5
    assert np.abs(xy[0] - neutral).max() > 10
    for region in ("eye_l", "eye_r", "brows"):
        assert (estimate.frames[region] >= 60).all(), region
    mouth = estimate.frames["mouth"]
    assert not (((mouth >= 30) & (mouth < 80)) | ((mouth >= 100) & (mouth < 110))).any()
    assert estimate.eye_open_known == {"eye_l": True, "eye_r": True}
    assert estimate.nearest_frame >= 80


def test_occluded_frames_never_enter_a_regions_neutral():
    """The mouth hidden in frames 80-119 (where it rests): its neutral comes from 0-29 and
    60-79 only... of which only 0-29 rest; the estimate stays within the noise."""
    layout = load_layout("zhang134")
    neutral, xy, shapes = clip_without_a_neutral_start(layout)
    hidden = np.arange(len(xy)) >= 80
    estimate = estimate_neutral(
        xy, layout.point_names, np.ones(len(xy), bool), shapes, BLENDSHAPE_NAMES, occluded={"mouth": hidden}
    )
    assert (estimate.frames["mouth"] < 80).all()
    assert np.abs(estimate.neutral - neutral).max() < 0.5


def test_eyes_shut_throughout_are_reported_as_unknown():
    layout = load_layout("zhang134")
    neutral, xy, shapes = clip_without_a_neutral_start(layout)
    upper = [layout.index(f"eye_l_{k}") for k in range(1, 6)]
    xy[:, upper, 1] = xy[0, upper, 1]  # the image-left eye shut in every frame
    estimate = estimate_neutral(xy, layout.point_names, np.ones(len(xy), bool), shapes, BLENDSHAPE_NAMES)
    assert estimate.eye_open_known == {"eye_l": False, "eye_r": True}


def test_open_eyes_of_a_clip_under_five_frames_are_known_open():
    """Three frames, eyes open in each: the open level is measured from them (not "shut in
    every frame" for want of five frames); shut in all three, it is still unknown."""
    layout = load_layout("zhang134")
    neutral, xy, shapes = clip_without_a_neutral_start(layout)
    short = xy[85:88]
    estimate = estimate_neutral(short, layout.point_names, np.ones(3, bool), shapes[85:88], BLENDSHAPE_NAMES)
    assert estimate.eye_open_known == {"eye_l": True, "eye_r": True}
    assert np.abs(estimate.neutral - neutral).max() < 1.0
    shut = estimate_neutral(xy[:3], layout.point_names, np.ones(3, bool), shapes[:3], BLENDSHAPE_NAMES)
    assert shut.eye_open_known == {"eye_l": False, "eye_r": False}


def test_point_regions_cover_every_point_once():
    layout = load_layout("zhang134")
    regions = point_regions(layout.point_names)
    counts = np.sum(list(regions.values()), axis=0)
    assert (counts == 1).all() and set(regions) == set(REGIONS) | {"rest"}
    names = np.array(layout.point_names)
    assert regions["eye_l"][list(names).index("eye_l_3")] and regions["mouth"][list(names).index("chin")]
    assert regions["rest"][list(names).index("nose_bridge_1")]


def test_hold_occluded_interpolates_holds_and_rests():
    d = np.zeros((10, 3, 2))
    d[:, 1, 0] = np.arange(10.0)  # a point moving 1 px a frame
    d[:, 2, 0] = 50.0  # not in the region: untouched
    hidden = np.zeros(10, bool)
    hidden[[0, 1, 4, 5, 6, 9]] = True
    out = hold_occluded(d, hidden, np.array([1]))
    np.testing.assert_allclose(out[:, 1, 0], [2, 2, 2, 3, 4, 5, 6, 7, 8, 8])  # held at the ends, lerp inside
    np.testing.assert_array_equal(out[:, 2], d[:, 2])
    d[4:7, 1, 0] = 99.0  # what an occluded run carried is never seen
    np.testing.assert_allclose(hold_occluded(d, hidden, np.array([1]))[4:7, 1, 0], [4, 5, 6])
    np.testing.assert_array_equal(hold_occluded(d, np.ones(10, bool), np.array([1]))[:, 1], 0.0)
    assert hold_occluded(d, np.zeros(10, bool), np.array([1])) is not d
