"""The bundled layout matches the paper's structure; broken layout files give clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from runner.stage import StageError
from stages.layout import LAYOUT_DIR, load_layout, parse_layout, subregion_mask


@pytest.fixture(scope="module")
def layout():
    return load_layout("zhang134")


def test_default_layout_structure(layout):
    assert layout.n_points == 134
    assert len(set(layout.point_names)) == 134
    face = [s for s in layout.subregions if not s.teeth]
    assert len(face) == 14 and layout.teeth_subregion is not None
    levels = [f.level for f in layout.feature_point_sets]
    assert (levels.count(0), levels.count(1), levels.count(2)) == (1, 4, 16)
    rigid = [layout.point_names[i] for i in layout.rigid]
    assert sorted(rigid) == sorted([f"hairline_{k}" for k in range(5)] + ["eye_l_0", "eye_r_0"])
    assert 27 <= len(layout.tracked) <= 40
    assert set(layout.rigid) <= set(layout.tracked)  # compensation needs the rigid points tracked
    names = {s.name for s in layout.subregions}
    assert all(a in names and b in names for a, b in layout.no_blend)
    assert ("eye_l", "eyezone_l") in layout.no_blend and ("lips", "philtrum") in layout.no_blend


def test_hierarchy_bridges_levels(layout):
    """Every level-1 set shares points with level 0 and with some level-2 set (Sec. 10 bridges)."""
    by_level = {k: [set(f.points) for f in layout.feature_point_sets if f.level == k] for k in (0, 1, 2)}
    for s in by_level[1]:
        assert s & by_level[0][0]
        assert any(s & t for t in by_level[2])
    covered = set().union(*by_level[2])
    assert covered == set(range(layout.n_points))


def test_index_and_subregion_lookup(layout):
    assert layout.point_names[layout.index("nose_tip")] == "nose_tip"
    assert layout.subregion("teeth").teeth
    with pytest.raises(KeyError):
        layout.index("no_such_point")
    lips = layout.subregion("lips")
    assert set(lips.all_points) == set(lips.polygon) | set(lips.points)


def test_subregions_tile_the_mean_face(layout):
    """Rasterized on the mean template, the subregions cover the face and land where named."""
    from stages.eigen.facegen.face import mean_template

    px = (mean_template(layout) + (100.0, 110.0)) * 2.0  # mm -> px, face inside a 400x460 image
    mask = subregion_mask(layout, px, (400, 460))
    contour = np.array(
        [
            px[layout.index(n)]
            for n in [f"contour_{k}" for k in range(17)]
            + ["temple_r"]
            + [f"hairline_{k}" for k in range(4, -1, -1)]
            + ["temple_l"]
        ]
    )
    import cv2

    face = np.zeros(mask.shape, np.uint8)
    cv2.fillPoly(face, [np.round(contour).astype(np.int32)], 1)
    uncovered = np.mean(mask[face > 0] < 0)
    assert uncovered < 0.01, uncovered
    names = [s.name for s in layout.subregions]

    def at(point_names):
        x, y = np.mean([px[layout.index(n)] for n in point_names], axis=0)
        return names[mask[int(round(y)), int(round(x))]]

    assert at(["eye_l_0", "eye_l_6"]) == "eye_l"
    assert at(["eye_r_0", "eye_r_6"]) == "eye_r"
    assert at(["forehead_c"]) == "forehead"
    assert at(["nose_bridge_2"]) == "nose"
    assert at(["cheek_l"]) == "cheek_l"
    assert at(["chin"]) == "chin"
    assert at(["mouth_outer_12", "mouth_inner_7"]) == "lips"


def _data() -> dict:
    return yaml.safe_load((LAYOUT_DIR / "zhang134.yaml").read_text())


@pytest.mark.parametrize(
    "edit, field",
    [
        (lambda d: d.pop("rigid"), "rigid"),
        (lambda d: d["points"].append(d["points"][0]), "points"),
        (lambda d: d["subregions"][0]["polygon"].append("no_such_point"), "subregions[0] (forehead).polygon"),
        (
            lambda d: d["subregions"][1]["polygon"].__setitem__(slice(None), ["glabella", "chin"]),
            "subregions[1] (glabella).polygon",
        ),
        (lambda d: d["no_blend"].append(["eye_l", "nowhere"]), "no_blend[7]"),
        (lambda d: d["feature_point_sets"][1].__setitem__("level", 0), "feature_point_sets"),
        (lambda d: d["feature_point_sets"][0].__setitem__("level", 3), "feature_point_sets[0].level"),
        (lambda d: d["tracked"].__setitem__(slice(None), ["chin"]), "tracked"),
    ],
)
def test_validation_names_the_field(edit, field):
    data = _data()
    edit(data)
    with pytest.raises(StageError) as err:
        parse_layout(data, source="broken.yaml")
    assert "broken.yaml" in str(err.value) and f"'{field}'" in str(err.value)


def test_point_in_no_feature_point_set_is_an_error():
    data = _data()
    data["points"].append("extra_point")
    with pytest.raises(StageError, match="extra_point"):
        parse_layout(data, source="x.yaml")


def test_unreadable_and_invalid_files(tmp_path: Path):
    with pytest.raises(StageError, match="cannot read"):
        load_layout(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("points: [a, b\n")
    with pytest.raises(StageError, match="not valid YAML"):
        load_layout(bad)
    bad.write_text("- just a list\n")
    with pytest.raises(StageError, match="mapping"):
        load_layout(bad)
