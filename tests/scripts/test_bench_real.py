"""The cross-identity sheet of ``bench.py real --target`` (scripts/bench_real.py): the performer is
drawn as its layout's lines, never as frame pixels; the drawing lands where the points are."""

from __future__ import annotations

import numpy as np

from scripts.bench_real import layout_polylines, points_panel
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
