"""Expression mapping's geometric step: displacements carried onto the target's neutral, normalized on
the eye corners and nose, limited to the pack's captured range, inner lips kept apart."""

from __future__ import annotations

import numpy as np
import pytest

from runner.stage import StageError
from stages.geometry.similarity import apply_similarity
from stages.geometry.mapping import (
    relative_range,
    NORMALIZATION_POINTS,
    ExpressionMap,
    captured_range,
    displacement_transforms,
    eye_distance,
    map_expression,
    separate_lips,
    soft_limit,
)
from stages.layout import load_layout
from tests.stages.geometry.synthetic import context, pack_inputs


def rotation(angle: float) -> np.ndarray:
    return np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])


def test_similarity_mode_scales_and_rotates_displacements():
    rng = np.random.default_rng(0)
    target = rng.uniform(50, 250, (12, 2))
    scale, angle = 0.6, 0.2
    # the performer's neutral: the target's face scaled by 1/0.6 and turned by -0.2 rad
    inverse = np.array([np.cos(-angle) / scale, np.sin(-angle) / scale, 30.0, -12.0])
    performer = apply_similarity(inverse, target)
    d = rng.normal(0, 4.0, (5, 12, 2))
    transforms = displacement_transforms(performer, target, np.arange(6))
    xy = map_expression(d, target, transforms)
    expected = target[None] + scale * np.einsum("ij,tnj->tni", rotation(angle), d)
    np.testing.assert_allclose(xy, expected, atol=1e-9)
    np.testing.assert_allclose(
        map_expression(d, target, displacement_transforms(performer, target, np.arange(6), mode="none")), target + d
    )


def test_region_mode_uses_each_region_size():
    rng = np.random.default_rng(1)
    performer = rng.uniform(0, 100, (9, 2))
    target = performer.copy()
    target[:4] = 2.0 * (performer[:4] - performer[:4].mean(axis=0)) + performer[:4].mean(axis=0)
    target[4:8] = 0.5 * (performer[4:8] - performer[4:8].mean(axis=0)) + performer[4:8].mean(axis=0)
    transforms = displacement_transforms(
        performer, target, np.arange(9), mode="region", regions=[np.arange(4), np.arange(4, 8), np.array([8])]
    )
    np.testing.assert_allclose(transforms[:4, 0, 0], 2.0, rtol=1e-12)
    np.testing.assert_allclose(transforms[4:8, 0, 0], 0.5, rtol=1e-12)
    np.testing.assert_allclose(transforms[:, 1, 0], 0.0, atol=1e-12)
    global_scale = displacement_transforms(performer, target, np.arange(9))[8]
    np.testing.assert_allclose(transforms[8], global_scale, atol=1e-12)  # too small a region: global


def test_stage_maps_onto_the_pack_neutral(tmp_path):
    layout = load_layout("zhang134")
    rng = np.random.default_rng(2)
    target_all = rng.uniform(40, 200, (layout.n_points, 2))
    pack = fake_pack(layout, target_all)
    names = np.array([layout.point_names[i] for i in layout.tracked])
    target = target_all[list(layout.tracked)]
    performer = apply_similarity(np.array([1.5, 0.0, 10.0, 5.0]), target)
    d = rng.normal(0, 3.0, (4, len(names), 2))
    bundle = {"d": d, "valid": np.ones((4, len(names)), bool), "names": names, "neutral": performer}
    bundle["valid"][2, 5] = False
    affine = {"lids": "displacement", "close_lips": False}  # every point size-scaled, the neutral as it is
    out = ExpressionMap().run({"displacements": bundle, **pack}, affine, context(tmp_path))["points"]
    tracked = list(layout.tracked)
    assert out["xy"].shape == (4, layout.n_points, 2) and list(out["names"]) == list(layout.point_names)
    guarded = [k for k, n in enumerate(names) if n.startswith(("eye_", "mouth_inner"))]  # random lids and lips cross
    free = [tracked[k] for k in range(len(tracked)) if k not in guarded]
    free_d = np.delete(d, guarded, axis=1)
    np.testing.assert_allclose(out["xy"][:, free], target_all[free] + free_d / 1.5, atol=1e-9)
    others = np.setdiff1d(np.arange(layout.n_points), tracked)
    np.testing.assert_array_equal(out["xy"][:, others], np.broadcast_to(target_all[others], (4, len(others), 2)))
    assert out["valid"][:, tracked].sum() == 4 * len(tracked) - 1 and not out["valid"][:, others].any()
    assert not out["valid"][2, tracked[5]]
    region = ExpressionMap().run({"displacements": bundle, **pack}, {"mode": "region", **affine}, context(tmp_path))["points"]
    np.testing.assert_allclose(region["xy"][:, free], target_all[free] + free_d / 1.5, atol=1e-9)  # one scale here
    del bundle["neutral"]
    with pytest.raises(StageError, match="neutral"):
        ExpressionMap().run({"displacements": bundle, **pack}, {}, context(tmp_path))


def fake_pack(layout, neutral: np.ndarray, captured: np.ndarray | None = None) -> dict:
    """The ``layout`` and ``geometry`` inputs of a pack with this neutral and these captured
    geometries (:func:`pack_inputs`)."""
    bundles = pack_inputs(layout, neutral=neutral, captured=captured)
    return {port: bundles[port] for port in ("layout", "geometry")}


def face(layout) -> np.ndarray:
    """A frontal face ``(N, 2)``: eye centres 100 px apart at y = 100, nose tip (150, 160), nose base
    (150, 175), hairline at y = 20, inner lips touching at y = 220; other points spread below."""
    xy = np.column_stack([np.linspace(60, 240, layout.n_points), np.linspace(200, 300, layout.n_points)])
    place = {
        "eye_l_0": (125, 100),
        "eye_l_6": (75, 100),
        "eye_r_0": (175, 100),
        "eye_r_6": (225, 100),
        "nose_tip": (150, 160),
        "nose_base": (150, 175),
    }
    place |= {f"hairline_{k}": (90 + 30 * k, 20) for k in range(5)}
    place |= {f"mouth_inner_{k}": (120 + 12 * k, 220) for k in range(1, 5)}
    place |= {f"mouth_inner_{k}": (240 - 12 * k, 220) for k in range(6, 10)}
    for name, value in place.items():
        xy[layout.index(name)] = value
    return xy


def test_eyes_nose_mode_ignores_a_low_stand_in_hairline(tmp_path):
    """The performer is the target at 1/1.5 the size, but its hairline points sit 20 px lower (a
    landmark mesh's stand-in): the rigid fit inflates the motion, the eye-and-nose fit does not."""
    layout = load_layout("zhang134")
    target_all = face(layout)
    pack = fake_pack(layout, target_all)
    names = np.array([layout.point_names[i] for i in layout.tracked])
    target = target_all[list(layout.tracked)]
    performer = apply_similarity(np.array([1 / 1.5, 0.0, 40.0, 30.0]), target)
    performer[[list(names).index(f"hairline_{k}") for k in range(5)], 1] += 20.0
    d = np.random.default_rng(3).normal(0, 3.0, (3, len(names), 2))
    bundle = {"d": d, "valid": np.ones((3, len(names)), bool), "names": names, "neutral": performer}
    tracked = list(layout.tracked)
    mapped = {
        mode: ExpressionMap().run({"displacements": bundle, **pack}, {"mode": mode, "lids": "displacement"}, context(tmp_path))[
            "points"
        ]
        for mode in ("eyes_nose", "similarity")
    }
    lips = [list(names).index(n) for n in ("mouth_inner_2", "mouth_inner_7", "eye_l_3", "eye_l_9", "eye_r_3", "eye_r_9")]
    others = np.setdiff1d(np.arange(len(names)), lips)  # the lip and lid guards may move them apart
    np.testing.assert_allclose(mapped["eyes_nose"]["xy"][:, tracked][:, others], (target + 1.5 * d)[:, others], atol=1e-9)
    inflated = np.linalg.norm(mapped["similarity"]["xy"][:, tracked] - target, axis=2).mean()
    assert inflated > 1.1 * np.linalg.norm(1.5 * d, axis=2).mean()
    del bundle["names"]
    bundle["names"] = np.array([n for n in names if n not in NORMALIZATION_POINTS[1:]])
    bundle["d"], bundle["neutral"] = d[:, : len(bundle["names"])], performer[: len(bundle["names"])]
    bundle["valid"] = bundle["valid"][:, : len(bundle["names"])]
    with pytest.raises(StageError, match="eyes_nose needs at least 2"):
        ExpressionMap().run({"displacements": bundle, **pack}, {}, context(tmp_path))


def test_soft_limit_by_hand():
    lo, hi = np.array([-2.0]), np.array([5.0])
    u = np.array([-5.0, -2.0, 3.0, 5.0, 9.0])
    expected = [-2.0 - 2.0 * 0.9051482536448664, -2.0, 3.0, 5.0, 5.0 + 2.0 * 0.9640275800758169]
    np.testing.assert_allclose(soft_limit(u, lo, hi, margin=2.0), expected, rtol=1e-12)
    np.testing.assert_array_equal(soft_limit(u, lo, hi, margin=0.0), [-2.0, -2.0, 3.0, 5.0, 5.0])
    assert soft_limit(np.array([1e6]), lo, hi, margin=2.0)[0] == pytest.approx(7.0)
    with pytest.raises(ValueError, match="margin"):
        soft_limit(u, lo, hi, margin=-1.0)
    neutral = np.zeros((2, 2))
    captured = np.array([[[1.0, 2.0], [-1.0, 0.5]], [[3.0, 1.0], [-2.0, 0.25]]])
    low, high = captured_range(captured, neutral)
    np.testing.assert_array_equal(low, [[0.0, 0.0], [-2.0, 0.0]])  # the neutral (0) is in every range
    np.testing.assert_array_equal(high, [[3.0, 2.0], [0.0, 0.5]])


def test_stage_range_limit_against_a_hand_computed_case(tmp_path):
    """The chin's captured vertical displacements span [-1, 4] px; the eye distance is 100 px, so a
    margin of 0.05 is 5 px: 2 px stays, 12 px becomes 4 + 5 tanh(8 / 5), -10 px -1 - 5 tanh(9 / 5)."""
    layout = load_layout("zhang134")
    neutral = face(layout)
    assert eye_distance(neutral, layout.point_names) == pytest.approx(100.0)
    chin = layout.index("chin")
    captured = np.repeat(neutral[None], 3, axis=0)
    captured[0, chin, 1] += 4.0
    captured[1, chin, 1] -= 1.0
    pack = fake_pack(layout, neutral, captured)
    names = np.array(["eye_l_0", "eye_r_0", "chin"])
    d = np.zeros((4, 3, 2))
    d[:, 2, 1] = [2.0, 12.0, -10.0, 8.0]  # 8 px: 4 beyond the range, inside the margin
    bundle = {"d": d, "valid": np.ones((4, 3), bool), "names": names, "neutral": neutral[[layout.index(n) for n in names]]}
    out = ExpressionMap().run({"displacements": bundle, **pack}, {"mode": "none", "range": "limit"}, context(tmp_path))["points"]
    expected = [2.0, 4.0 + 5.0 * np.tanh(8 / 5), -1.0 - 5.0 * np.tanh(9 / 5), 4.0 + 5.0 * np.tanh(4 / 5)]
    np.testing.assert_allclose(out["xy"][:, chin, 1] - neutral[chin, 1], expected, rtol=1e-12)
    np.testing.assert_array_equal(out["range_limited"], [False, True, True, False])
    off = ExpressionMap().run({"displacements": bundle, **pack}, {"mode": "none", "range": "none"}, context(tmp_path))["points"]
    np.testing.assert_allclose(off["xy"][:, chin, 1] - neutral[chin, 1], d[:, 2, 1])
    assert not off["range_limited"].any()
    margin = next(p for p in ExpressionMap.params if p.name == "range_margin")
    assert "out of range" in margin.problem(-0.1) and margin.problem(0.0) is None


def test_lips_of_a_performer_with_an_open_neutral_never_cross(tmp_path):
    """The performer's neutral frame has the mouth 6 px open; closing it fully (upper lip 4 px
    down, lower 2 px up) would push the target's touching lips 6 px through each other: the guard
    stops them where they touch on the target's neutral (its own 0.4 px overlap), each moved 3 px
    back."""
    layout = load_layout("zhang134")
    neutral = face(layout)
    upper, lower = layout.index("mouth_inner_3"), layout.index("mouth_inner_7")
    neutral[lower, 1] -= 0.4  # the target's neutral lips overlap a little (annotation)
    pack = fake_pack(layout, neutral)
    names = np.array([layout.point_names[i] for i in layout.tracked] + ["mouth_inner_3"])
    rows = [layout.index(n) for n in names]
    d = np.zeros((3, len(names), 2))
    up, low = list(names).index("mouth_inner_3"), list(names).index("mouth_inner_7")
    d[1, up, 1], d[1, low, 1] = 4.0, -2.0  # closes: crosses by 6 px
    d[2, up, 1], d[2, low, 1] = -2.0, 2.0  # opens: untouched
    bundle = {"d": d, "valid": np.ones((3, len(names)), bool), "names": names, "neutral": neutral[rows]}
    out = ExpressionMap().run({"displacements": bundle, **pack}, {}, context(tmp_path))["points"]
    gap = out["xy"][:, lower, 1] - out["xy"][:, upper, 1]
    np.testing.assert_allclose(gap, [-0.4, -0.4, 3.6], atol=1e-12)
    np.testing.assert_allclose(out["xy"][1, [upper, lower], 1] - neutral[[upper, lower], 1], [1.0, 1.0], atol=1e-12)
    np.testing.assert_array_equal(out["lips_clamped"], [False, True, False])
    np.testing.assert_allclose(out["xy"][0, rows], neutral[rows], atol=1e-12)  # neutral maps to itself
    bundle["valid"][1, low] = False  # an invalid partner: no guard, no count
    out = ExpressionMap().run({"displacements": bundle, **pack}, {}, context(tmp_path))["points"]
    assert not out["lips_clamped"].any()


def test_separate_lips_keeps_every_pair_apart():
    rng = np.random.default_rng(4)
    neutral = np.zeros((4, 2))
    xy = rng.normal(0, 3.0, (50, 4, 2))
    pairs = [(0, 2), (1, 2), (1, 3)]  # upper 1 faces two lower points
    out, clamped = separate_lips(xy, np.ones((50, 4), bool), neutral, pairs)
    for upper, lower in pairs:
        assert (out[:, lower, 1] - out[:, upper, 1] >= -1e-12).all()
    crossed = np.zeros(50, bool)
    for upper, lower in pairs:
        crossed |= xy[:, lower, 1] < xy[:, upper, 1]
    np.testing.assert_array_equal(clamped, crossed)
    np.testing.assert_array_equal(out[:, :, 0], xy[:, :, 0])  # only vertical moves
    np.testing.assert_array_equal(out[~crossed], xy[~crossed])


def test_the_log_names_the_points_limited_most(tmp_path, caplog):
    layout = load_layout("zhang134")
    neutral = face(layout)
    pack = fake_pack(layout, neutral, np.repeat(neutral[None], 2, axis=0))  # nothing moves in the pack
    names = np.array(["eye_l_0", "eye_r_0", "chin", "nose_tip"])
    d = np.zeros((5, 4, 2))
    d[1:, 2, 1] = 9.0  # chin: 4 frames 9 px beyond its (empty) range, margin 5 px
    d[3, 3, 0] = 6.0  # nose tip: 1 frame
    d[4, 3, 0] = 4.0  # inside the margin: softened, not counted
    bundle = {"d": d, "valid": np.ones((5, 4), bool), "names": names, "neutral": neutral[[layout.index(n) for n in names]]}
    with caplog.at_level("INFO"):
        out = ExpressionMap().run({"displacements": bundle, **pack}, {"mode": "none", "range": "limit"}, context(tmp_path))[
            "points"
        ]
    np.testing.assert_array_equal(out["range_limited"], [False, True, True, True, True])
    assert "in 4 of 5 frames (range=limit), most often (frames): chin 4, nose_tip 1;" in caplog.text
    assert out["xy"][4, layout.index("nose_tip"), 0] - neutral[layout.index("nose_tip"), 0] == pytest.approx(
        5.0 * np.tanh(4.0 / 5.0)
    )


def eyed_face(layout, *, eye_gap: float) -> np.ndarray:
    """:func:`face` with each eye's lids placed ``eye_gap`` px apart about the eye line (upper
    lid points 1-5 above, lower 7-11 below), the brows 40 px above the eye line with their inner
    ends (points 0 and 7) 50 px apart, and the outer lips an ellipse 60 x 16 px about the touching
    inner lips: a face whose states (:mod:`stages.geometry.states`) are defined."""
    xy = face(layout)
    for side, x0, sign in (("l", 125.0, -1.0), ("r", 175.0, 1.0)):
        for k in range(8):
            xy[layout.index(f"brow_{side}_{k}")] = (x0 + sign * 10 * min(k, 7 - k), 60.0)
    for side, (inner, outer) in (("l", (125, 75)), ("r", (175, 225))):
        for k in range(1, 6):
            x = inner + (outer - inner) * k / 6
            xy[layout.index(f"eye_{side}_{k}")] = (x, 100 - eye_gap / 2)
            xy[layout.index(f"eye_{side}_{12 - k}")] = (x, 100 + eye_gap / 2)
    for k in range(16):
        angle = np.pi * k / 8
        xy[layout.index(f"mouth_outer_{k}")] = (150 - 30 * np.cos(angle), 220 - 8 * np.sin(angle))
    return xy


def test_lids_close_by_the_performers_fraction_on_any_target(tmp_path):
    """The performer's eyes are 10 px open with the outer eye corners 150 px apart (0.067), the
    target's 16 px with them 225 px apart (0.071): a size-scaled closing leaves the target 1 px ajar; the lid ratio shuts it, halves
    it, widens it by the performer's fraction, and lids pushed past shut stop where they touch."""
    from stages.geometry.states import state_signals

    layout = load_layout("zhang134")
    performer = eyed_face(layout, eye_gap=10.0)
    target = apply_similarity(np.array([1.5, 0.0, -20.0, 10.0]), eyed_face(layout, eye_gap=16.0 / 1.5))
    pack = fake_pack(layout, target)
    names = np.array(layout.point_names)
    lids = np.array([n.startswith(("eye_l_", "eye_r_")) and n[6:] not in ("0", "6") for n in names])
    upper = np.array([n.startswith(("eye_l_", "eye_r_")) and n[6:] in ("1", "2", "3", "4", "5") for n in names])
    d = np.zeros((5, len(names), 2))
    for t, fraction in enumerate((1.0, 0.0, 0.5, 1.3, -0.4)):  # open, shut, half, wide, past shut
        d[t, upper, 1] = (1.0 - fraction) * 10.0  # the upper lid comes down
    bundle = {"d": d, "valid": np.ones(d.shape[:2], bool), "names": names, "neutral": performer}

    def gaps(params):
        out = ExpressionMap().run({"displacements": bundle, **pack}, params, context(tmp_path))["points"]
        return state_signals(out["xy"], names)["eye_open_l"] * 225.0  # px of the target

    np.testing.assert_allclose(gaps({}), [16.0, 0.0, 8.0, 16.0 * 1.3, 0.0], atol=1e-9)
    scaled = gaps({"lids": "displacement"})
    assert scaled[1] == pytest.approx(1.0) and scaled[4] == pytest.approx(0.0)  # ajar; the guard still holds
    assert lids.sum() == 20


def test_the_targets_neutral_lips_are_closed_before_mapping(tmp_path):
    """A pack neutral with the inner lips 6 px apart: a performer at rest (lips closed, no
    displacement) seals the target's lips; close_lips=false keeps the pack's gap."""
    from stages.geometry.states import state_signals

    layout = load_layout("zhang134")
    target = eyed_face(layout, eye_gap=10.0)
    for k in range(6, 10):
        target[layout.index(f"mouth_inner_{k}"), 1] += 6.0
    pack = fake_pack(layout, target)
    names = np.array(layout.point_names)
    bundle = {
        "d": np.zeros((2, len(names), 2)),
        "valid": np.ones((2, len(names)), bool),
        "names": names,
        "neutral": eyed_face(layout, eye_gap=10.0),
    }
    out = ExpressionMap().run({"displacements": bundle, **pack}, {}, context(tmp_path))["points"]
    np.testing.assert_allclose(state_signals(out["xy"], names)["mouth_open"], 0.0, atol=1e-12)
    kept = ExpressionMap().run({"displacements": bundle, **pack}, {"close_lips": False}, context(tmp_path))["points"]
    np.testing.assert_allclose(state_signals(kept["xy"], names)["mouth_open"], 6.0 / 150.0, atol=1e-12)


def test_relative_range_scales_the_performers_range_onto_the_packs():
    """The pack spans [-1, 4] px at a point; the clip goes to 8 and -0.5: the positive side is
    halved, the negative side (inside) kept, and only the frames beyond count."""
    d = np.zeros((4, 1, 2))
    d[:, 0, 1] = [2.0, 8.0, -0.5, 4.0]
    scaled, outside = relative_range(d, np.ones((4, 1), bool), np.array([[0.0, -1.0]]), np.array([[0.0, 4.0]]))
    np.testing.assert_allclose(scaled[:, 0, 1], [1.0, 4.0, -0.5, 2.0])
    np.testing.assert_array_equal(outside[:, 0], [False, True, False, False])


def test_states_beyond_the_pack_are_flagged_and_named(tmp_path, caplog):
    """A pack whose examples never shut the eyes: a performer who shuts them is flagged in those
    frames, named once in the log; a pack with a shut-eye example covers it."""
    layout = load_layout("zhang134")
    neutral = eyed_face(layout, eye_gap=10.0)
    names = np.array(layout.point_names)
    upper = np.array([n.startswith(("eye_l_", "eye_r_")) and n[6:] in ("1", "2", "3", "4", "5") for n in names])
    d = np.zeros((4, len(names), 2))
    d[2:, upper, 1] = 10.0
    bundle = {"d": d, "valid": np.ones(d.shape[:2], bool), "names": names, "neutral": neutral}
    pack = fake_pack(layout, neutral)
    with caplog.at_level("WARNING"):
        out = ExpressionMap().run({"displacements": bundle, **pack}, {}, context(tmp_path))["points"]
    states = list(out["state_names"])
    np.testing.assert_array_equal(out["beyond_pack"][:, states.index("eye_l_shut")], [False, False, True, True])
    assert "eye l shut 2 frames" in caplog.text and "eye r shut 2 frames" in caplog.text
    shut = neutral.copy()
    shut[upper, 1] += 10.0
    pack["geometry"] = dict(pack["geometry"], examples=np.stack([neutral, shut]))
    covered = ExpressionMap().run({"displacements": bundle, **pack}, {}, context(tmp_path))["points"]
    assert not covered["beyond_pack"][:, states.index("eye_l_shut")].any()


def test_an_eye_never_seen_open_is_mapped_against_a_typical_open_eye(tmp_path):
    """The performer's neutral has both eyes shut (a clip with the eyes shut throughout, told by
    ``eye_open_known``): displacements of zero keep the target's eyes shut, not at its open rest."""
    from stages.geometry.states import state_signals

    layout = load_layout("zhang134")
    performer = eyed_face(layout, eye_gap=1.0)  # shut
    pack = fake_pack(layout, eyed_face(layout, eye_gap=12.0))
    names = np.array(layout.point_names)
    bundle = {
        "d": np.zeros((2, len(names), 2)),
        "valid": np.ones((2, len(names)), bool),
        "names": names,
        "neutral": performer,
        "eye_open_known": np.array([False, False]),
    }
    out = ExpressionMap().run({"displacements": bundle, **pack}, {}, context(tmp_path))["points"]
    gap = state_signals(out["xy"], names)["eye_open_l"] * 150.0
    assert (gap < 0.15 * 12.0).all()  # 1 px of the performer's 0.11 * 150 px typical gap: 12 px * 1 / 16.5
    bundle["eye_open_known"] = np.array([True, True])
    opened = ExpressionMap().run({"displacements": bundle, **pack}, {}, context(tmp_path))["points"]
    np.testing.assert_allclose(state_signals(opened["xy"], names)["eye_open_l"] * 150.0, 12.0, atol=1e-9)
