"""Offline build (Sec. 5.2, 5.3, 7): weight map of eq. 7, subregion mask, aligned examples."""

import numpy as np
import pytest
import torch

from runner.stage import StageError
from stages.synthesis.build import blend_weight_map, build_synthesis_model, subregion_weights
from stages.synthesis.warp import warp_images
from tests.stages.synthesis.synthetic import H, W, make_pack


def half_planes() -> np.ndarray:
    region = np.zeros((20, 40), np.int16)
    region[:, 20:] = 1  # boundary between columns 19 and 20, i.e. at x = 19.5
    return region


def test_weight_map_is_a_linear_ramp_across_the_boundary():
    r, i1, i2 = blend_weight_map(half_planes(), n_labels=2, band_px=8.0, no_blend=set())
    w = subregion_weights(r, i1, i2, n_labels=2)
    np.testing.assert_allclose(w.sum(0), 1.0, atol=1e-6)
    x = np.arange(40)
    expected = np.clip(0.5 - (x - 19.5) / 8.0, 0, 1)  # weight of the left subregion
    np.testing.assert_allclose(w[0, 10], expected, atol=1e-4)
    assert (i1 == half_planes()).all()
    assert (i2[:, 16:24] == 1 - half_planes()[:, 16:24]).all() and (i2[:, :15] == 0).all()


def test_no_blend_pair_is_a_hard_edge():
    r, i1, i2 = blend_weight_map(half_planes(), n_labels=2, band_px=8.0, no_blend={(1, 0)})
    assert (r == 1).all() and (i1 == i2).all()


def test_zero_band_disables_blending():
    r, i1, i2 = blend_weight_map(half_planes(), n_labels=2, band_px=0.0, no_blend=set())
    assert (r == 1).all() and (i2 == i1).all()


@pytest.fixture(scope="module")
def model():
    return build_synthesis_model(make_pack(), band_px=6.0)


def test_model_shapes_and_mask(model):
    pack = make_pack()
    S = len(pack.layout.subregions)
    assert model["examples"].shape == (4, H, W, 3) and model["examples"].dtype == np.uint8
    assert model["teeth"].shape == (2, H, W, 3)
    assert model["region"].shape == (H, W)
    assert model["subregion_points"].shape == (S, 16) and model["subregion_teeth"].tolist() == [False] * 6 + [True]
    # the teeth square is painted over cell11, whose centre is inside it
    assert model["region"][50, 48] == S - 1 and model["region"][30, 28] == 0 and model["region"][2, 2] == S
    # no blending across the no_blend pairs: a teeth pixel next to cell11 keeps r = 1
    teeth = model["region"] == S - 1
    assert (model["blend_r"][teeth] == 1).all()
    w = subregion_weights(model["blend_r"], model["blend_i1"], model["blend_i2"], n_labels=S + 1)
    np.testing.assert_allclose(w.sum(0), 1.0, atol=1e-6)


def test_examples_are_aligned_to_the_standard_geometry(model):
    pack = make_pack()
    ex = pack.examples[2]
    anchors = model["anchors"]
    src = torch.from_numpy(np.concatenate([ex.points, anchors]))[None]
    dst = torch.from_numpy(np.concatenate([model["standard_points"], anchors]))[None]
    img = torch.from_numpy(ex.image).permute(2, 0, 1)[None].float()
    expected = warp_images(img, src, dst, model["triangles"])[0].permute(1, 2, 0).numpy()
    assert np.abs(model["examples"][2].astype(float) - expected).max() <= 0.5 + 1e-3  # uint8 rounding only
    # and not the identity: the example moved
    assert np.abs(model["examples"][2].astype(float) - ex.image).mean() > 1.0


def test_pack_without_teeth_examples_is_an_error():
    pack = make_pack()
    pack.teeth_examples = []
    with pytest.raises(StageError, match="teeth_examples"):
        build_synthesis_model(pack)


def test_the_head_ring_follows_a_head_wider_than_the_face_and_stays_at_the_neck():
    """A face (a light oval of points) inside a dark head of hair 1.8 times its hull, on a plain
    light background: the head ring's scale is where the hair ends (plus the margin) along the rays
    above the mouth, and the default below it, where the neck goes on (GrabCut finds the head;
    the truth is the drawn disc)."""
    import cv2

    from stages.synthesis.surround import RING_MARGIN, RING_SCALES, head_extent, head_ring

    size, centre = (384, 512), np.array([192.0, 240.0])
    angles = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    points = centre + np.column_stack([60 * np.cos(angles), 80 * np.sin(angles)])
    image = np.full((size[1], size[0], 3), (200, 215, 230), np.uint8)  # a light blue wall
    cv2.ellipse(image, tuple(centre.astype(int)), (108, 144), 0, 0, 360, (60, 40, 30), -1)  # hair: 1.8 x the face
    cv2.ellipse(image, tuple(centre.astype(int)), (60, 80), 0, 0, 360, (225, 180, 160), -1)  # skin
    face = np.ones(len(points), bool)
    scale = head_extent(image, points, face)
    ring_idx, hull_centre = head_ring(points, face)
    below = (points[ring_idx] - hull_centre)[:, 1] > 0.5 * 70.0
    assert below.any() and (~below).any()
    np.testing.assert_allclose(scale[ring_idx][below], RING_SCALES[0])
    np.testing.assert_allclose(scale[ring_idx][~below], 1.8 + RING_MARGIN, atol=0.08)
