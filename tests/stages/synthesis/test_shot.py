"""The whole shot on the fixture target pack: mattes, the fill, the head turn in depth, the outside
of the face, the mouth's triangulation and the teeth mix."""

from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from stages.actor_pack import load_pack
from stages.mesh3d.model import lift, target_depth
from stages.synthesis.build import build_synthesis_model, polygon_area
from stages.synthesis.synthesize import HeadTurn, Synthesizer
from stages.synthesis.warp import triangle_index_map

PACK = Path("fixtures/packs/target")


@pytest.fixture(scope="module")
def pack():
    return load_pack(PACK)


@pytest.fixture(scope="module")
def model(pack):
    return build_synthesis_model(pack)


@pytest.fixture(scope="module")
def synth(model):
    return Synthesizer(model)


def turn_about_pivot(pack, angles_deg):
    """A head turn of the fixture target about its head centre: HeadTurn and the depths."""
    names = np.array(pack.layout.point_names)
    depth, pivot, _, _ = target_depth(pack.model3d, pack.neutral.points, pack.intrinsics, names)
    R = Rotation.from_euler("YXZ", angles_deg, degrees=True).as_matrix()
    return HeadTurn(R[None], (pivot - R @ pivot)[None], depth, pack.intrinsics), depth


def test_triangulation_tiles_the_image_once_and_keeps_the_teeth_inside_the_mouth(model):
    """Every pixel of the standard geometry is in exactly one triangle; no triangle joins a teeth
    point to a point outside the inner lips (such a triangle, squeezed when the mouth closes, put
    white teeth specks at the mouth corners)."""
    W, H = (int(v) for v in model["size"])
    vertices = np.concatenate([model["standard_points"], model["anchors"]])
    covered = np.zeros((H, W), np.int32)
    for k in range(len(model["triangles"])):
        covered += triangle_index_map(vertices, model["triangles"][k : k + 1], (W, H), uncovered=-1) == 0
    assert covered.min() >= 1
    from matplotlib.path import Path as PolygonPath

    names = list(model["point_names"])
    std = model["standard_points"]
    outline = PolygonPath(std[model["teeth_polygon"]])
    teeth = {i for i, n in enumerate(names) if n.startswith("teeth_") and outline.contains_point(std[i])}
    assert len(teeth) >= 4
    lips = set(model["teeth_polygon"].tolist())
    for tri in model["triangles"]:
        if teeth & set(tri.tolist()):
            assert set(tri.tolist()) <= teeth | lips
    # the image's edge maps onto itself when only the feature points move (example alignment)
    edge = model["anchor_kind"] == 0
    on_edge = model["anchors"][edge]
    assert np.isclose(on_edge[:, 0], -0.5).any() and np.isclose(on_edge[:, 1], H - 0.5).any()


def test_outside_of_the_face_is_the_neutral_not_the_standard(pack):
    """The standard image's jaw is dropped furthest; its jaw edge (here a dark band painted just
    below its chin, outside the face outline) came out below the synthesized face in every frame (a
    "double chin"). At the neutral geometry the frame outside the face is the neutral image."""
    import cv2
    from dataclasses import replace

    names = list(pack.layout.point_names)
    image = pack.standard.image.copy()
    chin = pack.standard.points[[names.index(f"contour_{k}") for k in range(5, 12)]]
    cv2.polylines(image, [np.round(chin + [0, 6]).astype(np.int32)], False, (20, 10, 10), 4)
    shadowed = replace(pack, standard=replace(pack.standard, image=image))
    synth = Synthesizer(build_synthesis_model(shadowed))
    rgba, mattes, _ = synth.render_rgba(pack.neutral.points[None], mode="full")
    rgb = rgba[0, :3].permute(1, 2, 0).numpy()
    outside = (rgba[0, 3].numpy() < 0.01) & (mattes[0, 0].numpy() > 0.999)
    below = np.zeros_like(outside)
    neutral_chin = pack.neutral.points[[names.index(f"contour_{k}") for k in range(5, 12)]]
    cv2.polylines(below.view(np.uint8), [np.round(neutral_chin + [0, 8]).astype(np.int32)], False, 1, 12)
    region = outside & below
    assert region.sum() > 50
    assert np.abs(rgb - pack.neutral.image / 255.0)[region].mean() < 0.02


def test_a_head_turn_moves_near_points_more_than_far_ones(pack, synth):
    """Yaw about the head centre: the nose tip (nearest) moves sideways more than the face contour,
    the background corners stay; the frame is whole, its mattes in range."""
    turn, depth = turn_about_pivot(pack, (20.0, 0.0, 0.0))
    points = pack.neutral.points[None]
    dst, triangles = synth._destinations(points, None, turn, source_center=None, target_center=None, motion_scale=1.0)
    names = list(pack.layout.point_names)
    nose, contour = names.index("nose_tip"), names.index("contour_8")
    shift = dst[0, : len(names), 0] - points[0, :, 0]
    assert abs(shift[nose]) > abs(shift[contour]) + 3.0
    assert depth[nose] < depth[contour]
    corners = np.flatnonzero(synth.anchor_kind == 0)
    np.testing.assert_allclose(dst[0, len(names) + corners], synth.anchors[corners], atol=1e-9)
    rgba, mattes, _ = synth.render_rgba(points, turn=turn)
    assert rgba.shape[2:] == mattes.shape[2:] and 0 <= float(mattes.min()) and float(mattes.max()) <= 1


def test_turned_projection_is_the_3d_motion(pack, synth):
    """The warp's destination of every feature point is the projection of the lifted point moved
    by X' = R X + t (what the 3D render does to the mesh)."""
    turn, depth = turn_about_pivot(pack, (15.0, -8.0, 5.0))
    points = pack.standard.points[None]
    dst, _ = synth._destinations(points, None, turn, source_center=None, target_center=None, motion_scale=1.0)
    X = lift(points[0], depth, pack.intrinsics) @ turn.R[0].T + turn.t[0]
    p = X @ pack.intrinsics.T
    np.testing.assert_allclose(dst[0, : len(depth)], p[:, :2] / p[:, 2:], atol=1e-9)


@pytest.mark.parametrize("angles", [(30.0, 0.0, 0.0), (-30.0, 10.0, 0.0), (0.0, 0.0, 25.0)])
def test_the_surround_never_paints_over_the_face(pack, synth, angles):
    """Whatever depth the head ring's anchors are given, the pixels the turned face's triangles
    cover are the face's: the painter's last triangle there has no anchor corner (the triangle
    index map of the warp, painted in the returned order, read against the face triangles' own
    coverage)."""
    turn, _ = turn_about_pivot(pack, angles)
    points = pack.neutral.points[None]
    dst, order = synth._destinations(points, None, turn, source_center=None, target_center=None, motion_scale=1.0)
    n = len(pack.layout.point_names)
    surround = (order[0] >= n).any(axis=1)
    assert surround.any() and (~surround).any()
    assert not surround[np.argmax(~surround) :].any()  # every surround triangle before every face triangle
    size = synth.out_size
    winner = triangle_index_map(dst[0], order[0], size, uncovered=-1)
    face_only = triangle_index_map(dst[0], order[0][~surround], size, uncovered=-1)
    covered = face_only >= 0
    assert covered.sum() > 1000
    assert not surround[winner[covered]].any()


def test_pixels_from_beyond_the_pack_image_are_marked_and_filled(pack, model):
    """A similarity moving the image 40 px right: the strip it leaves has no source. It is marked
    filled (1), the rest not (0), and its colour is no copy of the image's edge column."""
    synth = Synthesizer(model)
    sim = np.array([[1.0, 0.0, 40.0, 0.0]])
    frames, mask, head, filled, _ = synth.render_half(pack.neutral.points[None], similarity=sim)
    f = filled[0, ..., 0].astype(np.float32)
    assert (f[:, :30] > 0.99).all() and (f[:, 50:] < 0.01).all()
    strip = frames[0, :, :30].astype(np.float32)
    edge_column = frames[0, :, 41:42].astype(np.float32)
    assert np.abs(strip - edge_column).mean() > 0.01  # not the edge repeated: the fill varies across it


def test_teeth_mix_shows_lips_not_squeezed_teeth_in_a_nearly_closed_mouth(pack, model, synth):
    """The inner lips 2 px apart (under the least open teeth example's opening): the slit between
    them is mostly the face examples' lips, not the teeth examples squeezed into it (on real packs,
    a white line along the lips)."""
    from stages.layout import subregion_mask
    from stages.synthesis.composite import composite
    from stages.synthesis.warp import warp_images

    names = list(pack.layout.point_names)
    points = pack.neutral.points.copy()
    points[[names.index(f"mouth_inner_{k}") for k in (6, 7, 8)], 1] += 2.0
    a0, a1 = model["teeth_open_area"]
    assert a0 < polygon_area(points[model["teeth_polygon"]]) < a1
    coeffs = synth.coefficients(points[None])
    dst = torch.from_numpy(np.concatenate([points, synth.anchors])[None])

    def slit(teeth_mix):
        standard = composite(synth.compositor, coeffs, teeth_mix=teeth_mix)
        frame = warp_images(standard, synth.standard_points[None], dst, synth.triangles)[0, :3].permute(1, 2, 0).numpy()
        return frame[region].mean()

    region = subregion_mask(pack.layout, points, synth.size) == pack.layout.subregions.index(pack.layout.teeth_subregion)
    assert region.sum() > 5
    assert synth.teeth_mix(points[None])[0] < 0.2
    rendered = synth.render_rgba(points[None])[0][0, :3].permute(1, 2, 0).numpy()[region].mean()
    assert rendered == pytest.approx(slit(synth.teeth_mix(points[None])), abs=1e-5)
    lips, teeth = slit(np.zeros(1)), slit(None)  # the face examples alone, the teeth examples alone
    assert abs(teeth - lips) > 0.01
    assert abs(rendered - lips) < 0.3 * abs(teeth - lips)


@pytest.mark.slow
def test_output_width_is_a_parameter_and_a_size_the_footage_does_not_hold_is_refused(pack, model):
    from runner.stage import Context, StageError
    from stages.synthesis.synthesize import Synthesize
    from tests.memory_stream import process_once

    W, H = pack.image_size
    points = np.asarray(pack.captured_points[:2], np.float64)
    inputs = {"model": model, "points": {"xy": points, "valid": np.ones(points.shape[:2], bool)}}
    params = {p.name: p.default for p in Synthesize.params}
    ctx = Context(device="cpu", files_dir=lambda port: None)
    half = process_once(Synthesize(), 0, 2, inputs, {**params, "width": W // 2}, ctx)
    assert half["frames"].shape == (2, H // 2, W // 2, 3) and half["filled"].shape == (2, H // 2, W // 2, 1)
    full = process_once(Synthesize(), 0, 2, inputs, params, ctx)
    import cv2

    small = cv2.resize(full["frames"][0].astype(np.float32), (W // 2, H // 2), interpolation=cv2.INTER_AREA)
    assert np.abs(small - half["frames"][0].astype(np.float32)).mean() < 0.02  # the same picture, smaller
    with pytest.raises(StageError, match=rf"parameter 'width': a {2 * W}x{2 * H} output enlarges 2.00x what the footage holds"):
        process_once(Synthesize(), 0, 2, inputs, {**params, "width": 2 * W}, ctx)
    big = process_once(Synthesize(), 0, 1, inputs, {**params, "width": 2 * W, "upscale": True}, ctx)
    assert big["frames"].shape == (1, 2 * H, 2 * W, 3)
    scaled = dict(model, source_scale=np.float64(0.5))  # a pack cut at half the footage's resolution
    twice = process_once(Synthesize(), 0, 1, {**inputs, "model": scaled}, {**params, "width": 2 * W}, ctx)
    assert twice["frames"].shape == (1, 2 * H, 2 * W, 3)
