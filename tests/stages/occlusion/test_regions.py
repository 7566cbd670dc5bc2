"""Which layout points each face region covers (``stages.occlusion.regions``)."""

import numpy as np

from stages.layout import load_layout
from stages.occlusion.regions import REGION_OUTLINES, REGIONS, region_points

NAMES = load_layout("zhang134").point_names


def covered(region: str) -> set[str]:
    row = region_points(NAMES)[REGIONS.index(region)]
    return {NAMES[i] for i in np.flatnonzero(row)}


def test_regions_cover_their_layout_points_and_nothing_else():
    assert covered("mouth") == (
        {f"mouth_outer_{k}" for k in range(16)}
        | {f"mouth_inner_{k}" for k in range(10)}
        | {f"teeth_upper_{k}" for k in range(4)}
        | {f"teeth_lower_{k}" for k in range(4)}
    )
    for side in "lr":
        assert covered(f"eye_{side}") == {f"eye_{side}_{k}" for k in range(12)} | {f"crease_{side}_{k}" for k in range(3)}
        assert covered(f"brow_{side}") == {f"brow_{side}_{k}" for k in range(8)}
    assert covered("nose") == {n for n in NAMES if n.startswith("nose_")} and len(covered("nose")) == 13


def test_regions_are_disjoint_and_leave_the_rest_of_the_face():
    table = region_points(NAMES)
    assert table.shape == (len(REGIONS), len(NAMES)) and table.dtype == bool
    assert (table.sum(axis=0) <= 1).all()
    free = {NAMES[i] for i in np.flatnonzero(~table.any(axis=0))}
    assert {"chin", "cheek_l", "glabella", "hairline_2", "contour_8", "under_eye_l"} <= free


def test_a_layout_without_a_region_has_an_empty_row():
    table = region_points(["mouth_outer_0", "chin", "eye_r_3"])
    assert table[REGIONS.index("mouth")].tolist() == [True, False, False]
    assert table[REGIONS.index("eye_r")].tolist() == [False, False, True]
    assert not table[REGIONS.index("nose")].any() and not table[REGIONS.index("eye_l")].any()


def test_outlines_are_the_layouts_subregions_over_the_regions_points():
    layout = load_layout("zhang134")
    for region, subregion in REGION_OUTLINES.items():
        polygon = {NAMES[i] for i in layout.subregion(subregion).polygon}
        assert polygon <= covered(region), region
