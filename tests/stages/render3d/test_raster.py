"""The moderngl rasterizer against ground truth: texture reproduction, z-buffer, culling, depth, MSAA."""

import numpy as np
import pytest

from stages.render3d.raster import MeshRenderer

W, H = 64, 48
A = np.array([[100.0, 0.0, 31.5], [0.0, 100.0, 23.5], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def renderer():
    r = MeshRenderer((W, H), samples=4)
    yield r
    r.release()


def quad(z: float, half_w: float, half_h: float, *, tilt: float = 0.0) -> np.ndarray:
    """Corners of a rectangle seen centred, at depth ``z + tilt * x`` mm, top-left first, clockwise
    in (x, y-down) = counter-clockwise on screen by the facegen convention's signed area."""
    xy = np.array([[-half_w, -half_h], [half_w, -half_h], [half_w, half_h], [-half_w, half_h]])
    return np.column_stack([xy, z + tilt * xy[:, 0]])


def project(v: np.ndarray) -> np.ndarray:
    p = v @ A.T
    return p[:, :2] / p[:, 2:3]


FRONT = np.array([[0, 1, 2], [0, 2, 3]])


def test_frontal_plane_reproduces_the_texture(renderer):
    rng = np.random.default_rng(0)
    texture = rng.random((H, W, 3)).astype(np.float32)
    v = quad(500.0, 400.0, 300.0)  # covers the whole image
    rgba, _ = renderer.render(v, FRONT, project(v), texture, A)
    assert np.allclose(rgba[..., 3], 1.0)
    np.testing.assert_allclose(rgba[..., :3], texture, atol=2e-3)


def test_pack_mesh_at_identity_pose_matches_the_image_where_frontal(renderer):
    from stages.actor_pack import load_pack
    from stages.mesh3d.model import build_target_model

    pack = load_pack("fixtures/packs/target")
    model = build_target_model(pack, pack.model3d, pack.intrinsics)
    Wp, Hp = pack.image_size
    r = MeshRenderer((Wp, Hp), samples=4)
    try:
        rgba, depth = r.render(model.neutral, model.triangles, pack.neutral.points, pack.neutral.image, model.camera)
    finally:
        r.release()
    inside = rgba[..., 3] > 0.999
    assert inside.mean() > 0.2
    diff = rgba[..., :3][inside] - pack.neutral.image[inside] / 255.0
    psnr = -10 * np.log10(np.mean(diff**2))
    assert psnr > 35.0, psnr
    assert np.isfinite(depth[inside]).all() and not np.isfinite(depth[rgba[..., 3] == 0]).any()


def test_z_buffer_hides_the_farther_face_in_any_draw_order(renderer):
    near, far = quad(400.0, 100.0, 60.0), quad(600.0, 300.0, 200.0)
    v = np.vstack([near, far])
    uv = np.zeros((8, 2))
    uv[4:] = 1.0  # far quad samples the texture's right column (blue), near the left (red)
    texture = np.array([[[1.0, 0, 0], [0, 0, 1.0]]], np.float32)
    for tri in (np.vstack([FRONT, FRONT + 4]), np.vstack([FRONT + 4, FRONT])):
        rgba, depth = renderer.render(v, tri, uv, texture, A)
        centre = rgba[H // 2, W // 2]
        np.testing.assert_allclose(centre, [1, 0, 0, 1], atol=1e-3)
        assert depth[H // 2, W // 2] == pytest.approx(400.0, rel=1e-5)
        corner = rgba[2, 2]
        np.testing.assert_allclose(corner, [0, 0, 1, 1], atol=1e-3)
        assert depth[2, 2] == pytest.approx(600.0, rel=1e-5)


def test_back_face_is_culled_on_request_and_hidden_behind_a_front_face(renderer):
    v = quad(500.0, 100.0, 60.0)
    back = FRONT[:, ::-1]
    texture = np.ones((2, 2, 3), np.float32)
    rgba, _ = renderer.render(v, back, np.zeros((4, 2)), texture, A, cull_back=True)
    assert rgba[..., 3].max() == 0.0
    rgba, _ = renderer.render(v, back, np.zeros((4, 2)), texture, A, cull_back=False)
    assert rgba[H // 2, W // 2, 3] == pytest.approx(1.0)
    # a closed "box": a back face behind the front face never shows
    front_face, back_face = quad(400.0, 100.0, 60.0), quad(450.0, 100.0, 60.0)
    uv = np.zeros((8, 2))
    uv[4:] = 1.0
    tex = np.array([[[1.0, 0, 0], [0, 1.0, 0]]], np.float32)
    rgba, depth = renderer.render(np.vstack([front_face, back_face]), np.vstack([FRONT, back + 4]), uv, tex, A)
    np.testing.assert_allclose(rgba[H // 2, W // 2], [1, 0, 0, 1], atol=1e-3)


def test_depth_channel_is_camera_z_in_mm_on_a_tilted_plane(renderer):
    v = quad(500.0, 300.0, 300.0, tilt=0.3)
    _, depth = renderer.render(v, FRONT, np.zeros((4, 2)), np.ones((1, 1, 3), np.float32), A)
    u, w = np.meshgrid(np.arange(W), np.arange(H))
    dx = (u - A[0, 2]) / A[0, 0]
    truth = 500.0 / (1.0 - 0.3 * dx)  # z = 500 + 0.3 x along the ray x = z dx
    np.testing.assert_allclose(depth, truth, rtol=1e-4)


def test_msaa_gives_fractional_alpha_on_a_slanted_edge():
    v = np.array([[-50.0, -40.0, 500.0], [60.0, -40.0, 500.0], [-50.0, 45.0, 500.0]])
    tri = np.array([[0, 1, 2]])
    texture = np.ones((1, 1, 3), np.float32)
    with_msaa, plain = MeshRenderer((W, H), samples=4), MeshRenderer((W, H), samples=0)
    try:
        a4 = with_msaa.render(v, tri, np.zeros((3, 2)), texture, A)[0][..., 3]
        a1 = plain.render(v, tri, np.zeros((3, 2)), texture, A)[0][..., 3]
    finally:
        with_msaa.release()
        plain.release()
    partial = (a4 > 0.01) & (a4 < 0.99)
    assert partial.sum() > 10
    assert set(np.unique(a1)) <= {0.0, 1.0}
    assert abs(a4.sum() - a1.sum()) < 0.05 * a1.sum()


def test_bad_shapes_raise(renderer):
    with pytest.raises(ValueError, match="vertices"):
        renderer.render(np.zeros((4, 2)), FRONT, np.zeros((4, 2)), np.ones((1, 1, 3)), A)
    with pytest.raises(ValueError, match="triangles index"):
        renderer.render(np.zeros((4, 3)), FRONT + 2, np.zeros((4, 2)), np.ones((1, 1, 3)), A)
