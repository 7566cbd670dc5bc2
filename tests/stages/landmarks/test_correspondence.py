"""The layout-to-mesh correspondence: loader validation and the combination it computes."""

import copy

import numpy as np
import pytest
import yaml

from stages.landmarks.correspondence import layout_from_mesh, load_correspondence, parse_correspondence
from stages.layout import LAYOUT_DIR, load_layout

LAYOUT = load_layout("zhang134")
BUNDLED = yaml.safe_load((LAYOUT_DIR / "zhang134_mediapipe.yaml").read_text())


def parse(change):
    data = copy.deepcopy(BUNDLED)
    change(data)
    return parse_correspondence(data, layout=LAYOUT, source="c.yaml")


def test_bundled_correspondence_is_complete_and_affine():
    c = load_correspondence("zhang134_mediapipe")
    assert c.point_names == LAYOUT.point_names and c.weights.shape == (134, 478)
    np.testing.assert_allclose(c.weights.sum(axis=1), 1.0, atol=1e-9)
    # iris vertices (468-477) are not used: eye points follow the lids
    assert not c.weights[:, 468:].any()


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda d: d["points"].update(nose_tipp=1), "points.nose_tipp': unknown point name"),
        (lambda d: d["points"].pop("chin"), "points': no entry for layout point 'chin'"),
        (lambda d: d["points"].update(chin=478), "points.chin': vertex index 478 out of range"),
        (lambda d: d["points"].update(chin=-1), "points.chin': vertex index -1 out of range"),
        (lambda d: d["points"].update(chin={"vertices": [1, 2], "weights": [0.5, 0.6]}), "points.chin': weights sum to 1.1"),
        (lambda d: d["points"].update(chin={"vertices": [1, 2], "weights": [1.0]}), "points.chin': expected 2 finite weights"),
        (
            lambda d: d["points"].update(chin={"vertices": [1, 1], "weights": [0.5, 0.5]}),
            "points.chin': a vertex is listed twice",
        ),
        (
            lambda d: d["points"].update(chin={"vertices": [1], "weights": [1], "wieghts": 1}),
            "points.chin': unknown key 'wieghts'",
        ),
        (lambda d: d["points"].update(chin="152"), "points.chin': expected a vertex index"),
        (lambda d: d.pop("mesh_vertices"), "mesh_vertices': missing"),
    ],
)
def test_validation_errors_name_the_entry(change, message):
    with pytest.raises(ValueError, match="c.yaml: field '" + message.replace("(", r"\(")):
        parse(change)


def test_layout_from_mesh_is_the_weighted_sum_of_the_vertices():
    c = parse(
        lambda d: d["points"].update(
            hairline_2={"vertices": [10, 151], "weights": [1.5, -0.5]},
            chin=152,
            cheek_l={"vertices": [50, 205, 187], "weights": [0.2, 0.3, 0.5]},
        )
    )
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 500, (3, 478, 2))
    points = layout_from_mesh(xy, c)
    assert points.shape == (3, 134, 2)
    np.testing.assert_allclose(points[:, LAYOUT.index("hairline_2")], 1.5 * xy[:, 10] - 0.5 * xy[:, 151])
    np.testing.assert_array_equal(points[:, LAYOUT.index("chin")], xy[:, 152])
    np.testing.assert_allclose(points[:, LAYOUT.index("cheek_l")], 0.2 * xy[:, 50] + 0.3 * xy[:, 205] + 0.5 * xy[:, 187])
    # affine: a translation of the mesh translates every point
    np.testing.assert_allclose(layout_from_mesh(xy + (7.0, -3.0), c), points + (7.0, -3.0))


def test_layout_from_mesh_keeps_nan_frames_to_themselves():
    c = load_correspondence("zhang134_mediapipe")
    xy = np.zeros((2, 478, 2))
    xy[1] = np.nan
    xy[0, 470] = np.nan  # an unused iris vertex
    points = layout_from_mesh(xy, c)
    assert np.isfinite(points[0]).all() and np.isnan(points[1]).all()
    with pytest.raises(ValueError, match=r"\(T, 478, D\)"):
        layout_from_mesh(np.zeros((2, 468, 2)), c)
