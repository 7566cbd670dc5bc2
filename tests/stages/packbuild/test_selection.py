"""Frame selection for packs: similarity composition, the pack frame, greedy k-center (covering radius
against brute force, spread), and select_frames on known geometries (the fixture pack's examples seen
through random head motions)."""

import itertools

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stages.actor_pack import load_pack
from stages.geometry.compensate import apply_similarity
from stages.landmarks.landmarker import BLENDSHAPE_NAMES
from stages.packbuild.selection import FRAMINGS, canvas_similarity, compose_similarity, k_center, select_frames
from tests.stages.synthesis.test_fixture_pack import PACK


def optimal_radius(features, k, seed):
    """The smallest covering radius of any k centres that include ``seed`` (brute force)."""
    others = [i for i in range(len(features)) if i != seed]
    best = np.inf
    for rest in itertools.combinations(others, k - 1):
        centres = features[[seed, *rest]]
        radius = np.linalg.norm(features[:, None] - centres[None], axis=-1).min(axis=1).max()
        best = min(best, radius)
    return best


def test_compose_similarity_is_applying_one_after_the_other():
    rng = np.random.default_rng(0)
    inner, outer = rng.normal(size=4), rng.normal(size=4)
    xy = rng.normal(size=(7, 2)) * 50
    np.testing.assert_allclose(
        apply_similarity(compose_similarity(outer, inner), xy), apply_similarity(outer, apply_similarity(inner, xy)), atol=1e-9
    )


def test_k_center_on_a_line_picks_the_far_end_then_the_middle():
    features = np.arange(11.0)[:, None]
    chosen, radii = k_center(features, 3, seeds=[0])
    assert chosen == [0, 10, 5]
    assert radii == [10.0, 5.0, 2.0]


@pytest.mark.parametrize("seed_row", [0, 7])
def test_k_center_radius_within_twice_the_optimum_and_chosen_rows_spread(seed_row):
    rng = np.random.default_rng(seed_row)
    features = np.concatenate([rng.normal(c, 0.3, size=(4, 2)) for c in ((0, 0), (6, 0), (0, 6), (6, 6), (3, 12))])
    k = 5
    chosen, radii = k_center(features, k, seeds=[seed_row])
    assert len(chosen) == k and len(set(chosen)) == k
    # one centre per cluster: the clusters are 6 apart, their spread below 1.5
    assert {c // 4 for c in chosen} == set(range(5))
    nearest = np.linalg.norm(features[:, None] - features[chosen][None], axis=-1).min(axis=1)
    assert radii[-1] == pytest.approx(nearest.max())
    assert radii[-1] <= 2 * optimal_radius(features, k, seed_row) + 1e-12
    pairwise = np.linalg.norm(features[chosen][:, None] - features[chosen][None], axis=-1)
    assert pairwise[~np.eye(k, dtype=bool)].min() >= radii[-1]  # no two chosen closer than the radius
    assert all(a >= b for a, b in zip(radii, radii[1:]))


def test_k_center_stops_when_nothing_distinct_is_left():
    features = np.array([[0.0], [0.0], [0.1], [5.0], [5.05]])
    chosen, radii = k_center(features, 4, seeds=[0], min_distance=0.5)
    assert chosen == [0, 4] and radii[-1] == pytest.approx(0.1)  # 5.05 is the farthest; 5.0 is covered by it


def test_k_center_rejects_bad_arguments():
    with pytest.raises(ValueError, match="seed"):
        k_center(np.zeros((3, 2)), 2, seeds=[])
    with pytest.raises(ValueError, match="features"):
        k_center(np.zeros(3), 2, seeds=[0])


@pytest.fixture(scope="module")
def pack():
    return load_pack(PACK)


@pytest.mark.parametrize("framing", sorted(FRAMINGS))
def test_canvas_puts_the_eye_line_level_and_every_face_inside_at_the_framings_size(pack, framing):
    neutral = pack.neutral.points
    theta = np.radians(12)
    tilted = apply_similarity(np.array([0.8 * np.cos(theta), 0.8 * np.sin(theta), 30.0, -10.0]), neutral)
    geometries = np.stack([tilted, tilted + (0, 15)])
    params = canvas_similarity(tilted, geometries, pack.layout, (300, 400), framing=framing)
    placed = apply_similarity(params, geometries)
    left, right = (placed[0, pack.layout.index(n)] for n in ("eye_l_6", "eye_r_6"))
    assert abs(right[1] - left[1]) < 1e-9 and right[0] > left[0]
    lo, hi = placed.reshape(-1, 2).min(0), placed.reshape(-1, 2).max(0)
    assert np.all(lo >= -0.5) and hi[0] <= 299.5 and hi[1] <= 399.5
    # the box is from percentiles of the frames (1st of the minima, 99th of the maxima): about the fill,
    # centred across and its centre at the framing's height
    fill, centre = FRAMINGS[framing]
    assert max((hi[0] - lo[0]) / 300, (hi[1] - lo[1]) / 400) == pytest.approx(fill, abs=0.005)
    assert (lo[0] + hi[0]) / 2 == pytest.approx(299 / 2, abs=1.0)
    assert (lo[1] + hi[1]) / 2 == pytest.approx(centre * 399, abs=1.0)


def moving_clip(pack, repeats=3, noise_px=0.01, seed=0):
    """Each of the pack's neutral and example geometries ``repeats`` times under a random similarity
    (rotation up to 10 degrees, scale 0.8-1.2, shift up to 40 px) plus noise; (xy, cluster of each frame)."""
    rng = np.random.default_rng(seed)
    shapes = [pack.neutral.points] + [e.points for e in pack.examples]
    xy, cluster = [], []
    for c, shape in enumerate(shapes):
        for _ in range(repeats):
            angle, scale = np.radians(rng.uniform(-10, 10)), rng.uniform(0.8, 1.2)
            params = np.array([scale * np.cos(angle), scale * np.sin(angle), *rng.uniform(-40, 40, 2)])
            xy.append(apply_similarity(params, shape) + rng.normal(0, noise_px, shape.shape))
            cluster.append(c)
    order = rng.permutation(len(xy))
    return np.stack(xy)[order], np.array(cluster)[order]


def select(pack, xy, cluster, angles=None, **options):
    T = len(xy)
    blendshapes = np.where(cluster[:, None] == 0, 0.0, 0.3).astype(np.float32) * np.ones((T, len(BLENDSHAPE_NAMES)))
    return select_frames(
        xy,
        np.ones(T, bool),
        layout=pack.layout,
        blendshapes=blendshapes,
        blendshape_names=np.array(BLENDSHAPE_NAMES),
        matrix=np.tile(np.eye(4), (T, 1, 1)),
        angles=np.zeros((T, 3)) if angles is None else angles,
        teeth_fraction=np.full(T, 0.5),
        size=(240, 320),
        **options,
    )


def test_select_frames_one_example_per_distinct_expression_whatever_the_head_motion(pack):
    xy, cluster = moving_clip(pack)
    distinct = 1 + len(pack.examples)
    chosen = select(pack, xy, cluster, n_examples=distinct, n_captured=distinct + 3, n_teeth=2)
    assert cluster[chosen.neutral] == 0
    assert sorted(cluster[chosen.examples]) == list(range(distinct))
    assert chosen.examples[0] == chosen.neutral and chosen.captured[:distinct] == chosen.examples
    # the head motion is undone: frames of one expression land on the same pack points
    placed = np.stack([apply_similarity(chosen.to_pack[t], xy[t]) for t in range(len(xy))])
    for c in range(distinct):
        group = placed[cluster == c]
        assert np.abs(group - group[0]).max() < 0.2
    assert chosen.example_radius_px < 0.2  # every frame is a repeat of a chosen expression
    # the standard has the widest inner-lip gap, the teeth examples are open mouths
    assert chosen.mouth_open[chosen.standard] == pytest.approx(chosen.mouth_open.max())
    assert all(chosen.mouth_open[t] >= 0.08 for t in chosen.teeth) and len(chosen.teeth) == 2
    assert chosen.warnings == [
        f"{len(chosen.captured)} captured geometries instead of {distinct + 3}: no more distinct expressions"
    ]


def test_select_frames_warns_when_fewer_distinct_expressions_than_examples(pack):
    xy, cluster = moving_clip(pack)
    keep = cluster < 4
    chosen = select(pack, xy[keep], cluster[keep], n_examples=10, n_captured=30)
    assert len(chosen.examples) == 4
    assert any("only 4 distinct expressions" in w and "10 examples were asked" in w for w in chosen.warnings)


def test_select_frames_needs_two_usable_frames(pack):
    xy, cluster = moving_clip(pack, repeats=1)
    with pytest.raises(ValueError, match="1 usable frame"):
        select_frames(
            xy,
            np.arange(len(xy)) == 0,
            layout=pack.layout,
            blendshapes=np.zeros((len(xy), len(BLENDSHAPE_NAMES))),
            blendshape_names=np.array(BLENDSHAPE_NAMES),
            matrix=np.tile(np.eye(4), (len(xy), 1, 1)),
            angles=np.zeros((len(xy), 3)),
            teeth_fraction=np.zeros(len(xy)),
            size=(240, 320),
        )


def test_frames_turned_or_nodding_away_from_the_neutral_are_not_candidates(pack):
    xy, cluster = moving_clip(pack)
    angles = np.zeros((len(xy), 3))
    angles[cluster == 3] = (0.0, 12.0, 0.0)  # nodding: pitch 12 degrees from the neutral's
    angles[cluster == 5] = (-10.0, 0.0, 0.0)  # turned
    angles[cluster == 7] = (0.0, 0.0, 25.0)  # rolled: in the image plane, the similarity undoes it
    distinct = 1 + len(pack.examples)
    chosen = select(pack, xy, cluster, angles=angles, n_examples=distinct, n_captured=distinct, pose_deg=8.0)
    assert sorted(cluster[chosen.examples]) == [c for c in range(distinct) if c not in (3, 5)]
    assert not set(chosen.captured) & set(np.flatnonzero((cluster == 3) | (cluster == 5)))


def test_with_depth_a_nod_or_a_turn_is_not_an_expression(pack):
    """Each expression seen under head rotations up to 12 degrees (orthographic, depth from the generic
    model): with the depth the geometries are compared with the rotation removed in 3D, and every frame
    is a repeat of a chosen expression; without it the rotation reads as expression."""
    rng = np.random.default_rng(3)
    layout = pack.layout
    mm = np.linalg.norm(pack.model3d[layout.index("eye_l_6")] - pack.model3d[layout.index("eye_r_6")])
    px = np.linalg.norm(pack.neutral.points[layout.index("eye_l_6")] - pack.neutral.points[layout.index("eye_r_6")])
    z = pack.model3d[:, 2] * px / mm
    shapes = [pack.neutral.points] + [e.points for e in pack.examples]
    xy, depth, cluster = [], [], []
    for c, shape in enumerate(shapes):
        centre = shape.mean(0)
        for _ in range(3):
            R = Rotation.from_euler("YX", rng.uniform(-12, 12, 2), degrees=True).as_matrix()
            xyz = np.column_stack([shape - centre, z]) @ R.T
            xy.append(xyz[:, :2] + centre + rng.uniform(-20, 20, 2))
            depth.append(xyz[:, 2])
            cluster.append(c)
    xy, depth, cluster = np.stack(xy), np.stack(depth), np.array(cluster)
    distinct = len(shapes)
    flat = select(pack, xy, cluster, n_examples=distinct, n_captured=distinct)
    solid = select(pack, xy, cluster, n_examples=distinct, n_captured=distinct, depth=depth)
    assert sorted(cluster[solid.examples]) == list(range(distinct))
    assert solid.example_radius_px < 0.3 * flat.example_radius_px, (solid.example_radius_px, flat.example_radius_px)


def shut_eyes(pack, points: np.ndarray, sides: str) -> np.ndarray:
    """``points`` with the upper lid of each eye in ``sides`` moved onto the lower lid."""
    out = points.copy()
    for side in sides:
        for upper, lower in ((1, 11), (2, 10), (3, 9), (4, 8), (5, 7)):
            out[pack.layout.index(f"eye_{side}_{upper}")] = out[pack.layout.index(f"eye_{side}_{lower}")]
    return out


def test_states_seed_the_examples_and_never_a_blink_or_wink_as_neutral_or_standard(pack):
    """30 frames: the neutral, the pack's widest mouth opening with a wink, a blink scored least
    expressive by the blendshapes, and repeats of two other examples. Three examples by distance
    alone would pass the blink by (it moves only the lids); seeded by the states, the blink is one,
    the neutral has open eyes, the standard is the widest opening with both eyes open."""
    from stages.geometry.signals import expression_signals

    opening = expression_signals(np.stack([e.points for e in pack.examples]), pack.layout.point_names)["mouth_open"]
    order = np.argsort(-opening)
    widest, second = (pack.examples[k].points for k in order[:2])
    others = [pack.examples[k].points for k in order[-2:]]  # the two smallest openings
    shapes = [pack.neutral.points, shut_eyes(pack, widest, "l"), shut_eyes(pack, pack.neutral.points, "lr"), second]
    xy = np.stack([shapes[k % 4] for k in range(28)] + others)
    cluster = np.array([k % 4 for k in range(28)] + [4, 5])
    blendshapes = np.full((len(xy), len(BLENDSHAPE_NAMES)), 0.3, np.float32)
    blendshapes[cluster == 2] = 0.0  # the blink looks least expressive to the blendshapes
    chosen = select_frames(
        xy,
        np.ones(len(xy), bool),
        layout=pack.layout,
        blendshapes=blendshapes,
        blendshape_names=np.array(BLENDSHAPE_NAMES),
        matrix=np.tile(np.eye(4), (len(xy), 1, 1)),
        angles=np.zeros((len(xy), 3)),
        teeth_fraction=np.full(len(xy), 0.5),
        size=(240, 320),
        n_examples=3,
        n_captured=6,
        n_teeth=1,
    )
    assert cluster[chosen.neutral] in (0, 3, 4, 5)  # eyes open (the blink scored best)
    np.testing.assert_array_equal(xy[chosen.standard], second)  # the widest opening with both eyes open, not the wink
    assert 2 in cluster[chosen.examples]  # the blink: eyes shut are shown
    assert cluster[chosen.states["eye_l_shut"]] == 2 and cluster[chosen.states["eye_r_shut"]] == 2
