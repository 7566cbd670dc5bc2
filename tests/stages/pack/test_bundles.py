"""The pack's bundles round-trip to the objects they stand for, and wrong bundles name the key."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stages.actor_pack import load_pack
from stages.layout import load_layout
from stages.pack import bundles
from tests.stages.test_actor_pack import _make_pack


@pytest.fixture(scope="module")
def pack(tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("bundles") / "pack"
    _make_pack(root, np.random.default_rng(5))
    return load_pack(root)


def test_layout_round_trip():
    layout = load_layout("zhang134")
    assert bundles.layout_from_bundle(bundles.layout_to_bundle(layout)) == layout


def test_layout_bundle_is_canonical():
    """Equal layouts give equal bundles (sorted JSON), a different layout another."""
    layout = load_layout("zhang134")
    a, b = bundles.layout_to_bundle(layout), bundles.layout_to_bundle(load_layout("zhang134"))
    assert str(a["document"]) == str(b["document"])
    renamed = bundles.layout_to_bundle(type(layout)(**{**layout.__dict__, "name": "other"}))
    assert str(renamed["document"]) != str(a["document"])


def test_geometry_model3d_camera_round_trip(pack):
    geometry = bundles.geometry_from_bundle(bundles.geometry_to_bundle(pack))
    np.testing.assert_array_equal(geometry.neutral, pack.neutral.points)
    np.testing.assert_array_equal(geometry.captured, pack.captured_points)
    assert geometry.names == pack.layout.point_names and geometry.size == pack.image_size
    names = ["nose_tip", "eye_l_0"]
    rows = [pack.layout.index(n) for n in names]
    np.testing.assert_array_equal(bundles.model3d_from_bundle(bundles.model3d_to_bundle(pack), names), pack.model3d[rows])
    camera = bundles.camera_to_bundle(pack)
    np.testing.assert_array_equal(bundles.camera_from_bundle(camera, size=pack.image_size), pack.intrinsics)
    with pytest.raises(ValueError, match=r"intrinsics are for 40x30 images, the clip's frames are 80x60"):
        bundles.camera_from_bundle(camera, size=(80, 60))


def test_images_round_trip(pack):
    images = bundles.images_from_bundle(bundles.images_to_bundle(pack), pack.layout)
    assert images.path == "tiny" and images.image_size == pack.image_size
    for got, want in [
        (images.neutral, pack.neutral),
        (images.standard, pack.standard),
        *zip(images.examples, pack.examples),
        *zip(images.teeth_examples, pack.teeth_examples),
    ]:
        assert got.name == want.name
        np.testing.assert_array_equal(got.image, want.image)
        np.testing.assert_array_equal(got.points, want.points)
    assert len(images.examples) == 2 and len(images.teeth_examples) == 1


def test_wrong_bundles_name_the_key(pack):
    geometry = bundles.geometry_to_bundle(pack)
    with pytest.raises(ValueError, match=r"pack_geometry bundle: expected key 'captured'"):
        bundles.geometry_from_bundle({k: v for k, v in geometry.items() if k != "captured"})
    with pytest.raises(ValueError, match=r"key 'neutral': expected shape \(134, 2\), got \(3, 2\)"):
        bundles.geometry_from_bundle({**geometry, "neutral": np.zeros((3, 2))})
    with pytest.raises(ValueError, match=r"pack_model3d bundle: expected points \['no_such'\]"):
        bundles.model3d_from_bundle(bundles.model3d_to_bundle(pack), ["no_such"])
    with pytest.raises(ValueError, match=r"layout bundle: key 'document': expected JSON"):
        bundles.layout_from_bundle({"name": np.array("x"), "document": np.array("{")})
    with pytest.raises(ValueError, match=r"layout bundle: field 'subregions': missing"):
        bundles.layout_from_bundle({"name": np.array("x"), "document": np.array('{"name": "x", "points": ["a"]}')})
    other = bundles.layout_to_bundle(load_layout("zhang134"))
    layout = bundles.layout_from_bundle(other)
    with pytest.raises(ValueError, match=r"key 'names': expected the 134 points of layout"):
        bundles.layout_and_geometry(other, {**geometry, "names": geometry["names"][::-1]})
    assert bundles.layout_and_geometry(other, geometry)[0] == layout


def test_bundles_hold_no_path(pack):
    """Moving a pack folder changes no bundle: no array holds the folder's path."""
    for bundle in bundles.pack_to_bundles(pack).values():
        for value in bundle.values():
            if value.dtype.kind == "U":
                assert not any(str(Path(pack.path)) in str(v) for v in np.ravel(value))
