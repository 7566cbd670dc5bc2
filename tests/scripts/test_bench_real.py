"""``bench.py real`` (scripts/bench_real.py): the cross-identity sheet draws the performer as its
layout's lines, never as frame pixels, where the points are; a clip's state rows are the worst
over its targets and no name is given two meanings."""

from __future__ import annotations

import numpy as np

from scripts import bench_real
from scripts.bench_real import frontal_points, layout_polylines, points_panel
from stages.layout import load_layout

NAMES = list(load_layout("zhang134").point_names)


def test_polylines_cover_every_point_once_in_order():
    runs = layout_polylines(NAMES)
    columns = np.concatenate([c for c, _ in runs])
    assert sorted(columns) == list(range(len(NAMES)))
    by_first = {NAMES[c[0]].rpartition("_")[0] or NAMES[c[0]]: (c, closed) for c, closed in runs}
    eye, closed = by_first["eye_l"]
    assert closed and [NAMES[c] for c in eye] == [f"eye_l_{k}" for k in range(12)]
    contour, closed = by_first["contour"]
    assert not closed and [NAMES[c] for c in contour] == [f"contour_{k}" for k in range(17)]
    assert ([NAMES[c] for c in by_first["chin"][0]], by_first["chin"][1]) == (["chin"], False)


def test_points_panel_draws_the_lines_where_the_points_are():
    side = 101
    xy = np.full((len(NAMES), 2), 50.0)  # every point at the centre of the box ...
    contour = [NAMES.index(f"contour_{k}") for k in range(17)]
    xy[contour] = np.stack([np.linspace(10, 90, 17), np.full(17, 80.0)], axis=1)  # ... but a horizontal jaw line
    panel = points_panel(xy, NAMES, side, box=np.array([0.0, 0.0, 100.0, 100.0]))
    assert panel.shape == (side, side, 3) and panel.dtype == np.uint8
    drawn = panel[..., 0] > 200
    assert drawn[80, 15:86].all()  # the jaw line, box px = panel px here
    assert drawn[45:56, 45:56].any()  # the dot of the collapsed points
    assert not drawn[:40].any() and not drawn[85:].any()  # nothing elsewhere: grey background
    assert (panel[:40] == 128).all()


def test_points_panel_of_a_frame_without_face_is_plain_grey():
    panel = points_panel(np.full((len(NAMES), 2), np.nan), NAMES, 32, box=np.array([0.0, 0.0, 10.0, 10.0]))
    assert (panel == 128).all()


def test_frontal_points_take_the_head_rotation_out():
    """Points of one rigid face seen under known head rotations come back to the reference
    frame's view (centred), whatever the rotation; scipy builds the rotations."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(4)
    face = rng.normal(size=(20, 3)) * [40.0, 50.0, 20.0]
    R = Rotation.from_euler("YXZ", [[0, 0, 0], [25, -10, 5], [-15, 20, -8]], degrees=True).as_matrix()
    seen = np.einsum("tij,nj->tni", R, face) + [[[300.0, 200.0, 900.0]]]
    frontal = frontal_points(seen[..., :2], seen[..., 2], 2.0 * R, reference=1)  # a scaled matrix, as MediaPipe's
    expected = ((face - face.mean(axis=0)) @ R[1].T)[:, :2]
    np.testing.assert_allclose(frontal, np.broadcast_to(expected, frontal.shape), atol=1e-9)


def test_a_clips_worst_state_is_the_worst_over_its_targets_and_never_a_follow_rows_name():
    measured = {
        "bundled": {"eyes_shut_recall": 0.9, "eyes_shut_frames": 10.0, "mouth_follow_r": 0.8, "mouth_amp_ratio": 1.1},
        "LP_d18": {"eyes_shut_recall": 0.7, "eyes_shut_frames": 12.0, "mouth_follow_r": 0.6, "lid_follow_r": float("nan")},
    }
    assert bench_real.worst_over_targets(measured) == {"eyes_shut_recall": 0.7, "eyes_shut_frames": 12.0}
