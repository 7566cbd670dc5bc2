"""Triangulation-based warp (Sec. 5.2) against identity, a global affine and per-triangle OpenCV."""

import cv2
import numpy as np
import pytest
import torch

from stages.synthesis.warp import Buffers, backward_map, border_anchors, triangle_index_map, triangulate, warp_images

W, H = 96, 80


def smooth_image() -> np.ndarray:
    """(H, W, 3) float32 in [0, 1]: smooth gradients and waves (bilinear is accurate on it)."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    return np.stack([0.5 + 0.4 * np.sin(x / 7.0) * np.cos(y / 9.0), x / W, 0.5 + 0.3 * np.cos((x + y) / 11.0)], -1).astype(
        np.float32
    )


def face_points(rng: np.random.Generator, n: int = 20) -> np.ndarray:
    return np.stack([rng.uniform(15, W - 15, n), rng.uniform(15, H - 15, n)], 1)


def to_tensor(image: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(image).permute(2, 0, 1)[None]


def test_border_anchors_cover_the_image():
    rng = np.random.default_rng(0)
    pts = np.concatenate([face_points(rng), border_anchors((W, H), per_side=3)])
    tri = triangulate(pts)
    index = triangle_index_map(pts, tri, (W, H))
    assert (index >= 0).all()
    assert border_anchors((W, H), per_side=3).shape == (12, 2)


def test_identity_warp_returns_the_image():
    rng = np.random.default_rng(1)
    pts = np.concatenate([face_points(rng), border_anchors((W, H))])
    tri = triangulate(pts)
    p = torch.from_numpy(pts)[None]
    out = warp_images(to_tensor(smooth_image()), p, p, tri)
    np.testing.assert_allclose(out[0].permute(1, 2, 0).numpy(), smooth_image(), atol=1e-5)


def test_global_affine_matches_cv2_warp_affine():
    rng = np.random.default_rng(2)
    src = np.concatenate([face_points(rng), border_anchors((W, H), margin=0.3)])
    A = np.array([[0.95, -0.12, 6.0], [0.1, 1.05, -4.0]])  # src -> dst
    dst = src @ A[:, :2].T + A[:, 2]
    tri = triangulate(src)
    out = warp_images(to_tensor(smooth_image()), torch.from_numpy(src)[None], torch.from_numpy(dst)[None], tri)
    ref = cv2.warpAffine(smooth_image(), A, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    grid, covered = backward_map(torch.from_numpy(src)[None], torch.from_numpy(dst)[None], tri, (W, H), dtype=torch.float64)
    assert bool(covered.all())
    # the backward map is the inverse affine exactly
    ys, xs = np.mgrid[0:H, 0:W]
    Ainv = cv2.invertAffineTransform(A)
    np.testing.assert_allclose(grid[0, ..., 0].numpy(), Ainv[0, 0] * xs + Ainv[0, 1] * ys + Ainv[0, 2], atol=1e-9)
    np.testing.assert_allclose(grid[0, ..., 1].numpy(), Ainv[1, 0] * xs + Ainv[1, 1] * ys + Ainv[1, 2], atol=1e-9)
    normalised, _ = backward_map(
        torch.from_numpy(src)[None], torch.from_numpy(dst)[None], tri, (W, H), dtype=torch.float64, source_size=(W, H)
    )
    torch.testing.assert_close(normalised, grid * torch.tensor([2.0 / (W - 1), 2.0 / (H - 1)], dtype=torch.float64) - 1.0)
    inside = (grid[0, ..., 0] > 1) & (grid[0, ..., 0] < W - 2) & (grid[0, ..., 1] > 1) & (grid[0, ..., 1] < H - 2)
    diff = np.abs(out[0].permute(1, 2, 0).numpy() - ref)[inside.numpy()]
    assert diff.max() < 5e-3  # cv2 interpolates with 1/32 px fixed-point weights


def test_piecewise_warp_matches_per_triangle_opencv():
    rng = np.random.default_rng(3)
    gy, gx = np.mgrid[20 : H - 15 : 15, 18 : W - 15 : 18].astype(np.float64)
    inner = np.stack([gx.ravel(), gy.ravel()], 1) + rng.uniform(-3, 3, size=(gx.size, 2))  # no slivers
    src = np.concatenate([inner, border_anchors((W, H), per_side=2)])
    dst = src.copy()
    dst[: len(inner)] += rng.normal(0, 2.0, size=inner.shape)  # move the inner points, keep the anchors
    tri = triangulate(src)

    def signed_area(p: np.ndarray) -> np.ndarray:
        e1, e2 = p[tri[:, 1]] - p[tri[:, 0]], p[tri[:, 2]] - p[tri[:, 0]]
        return e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]

    assert (np.sign(signed_area(src)) == np.sign(signed_area(dst))).all()  # no fold-over: one answer per pixel
    image = smooth_image()
    out = warp_images(to_tensor(image), torch.from_numpy(src)[None], torch.from_numpy(dst)[None], tri)[0].permute(1, 2, 0).numpy()
    checked = 0
    for k, t in enumerate(tri):
        M = cv2.getAffineTransform(src[t].astype(np.float32), dst[t].astype(np.float32))
        ref = cv2.warpAffine(image, M, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        mask = np.zeros((H, W), np.uint8)
        cv2.fillConvexPoly(mask, np.round(dst[t] * 16).astype(np.int32), 1, shift=4)
        mask = cv2.erode(mask, np.ones((3, 3), np.uint8)).astype(bool)  # pixels well inside triangle k
        if mask.any():
            assert np.abs(out[mask] - ref[mask]).max() < 5e-3, k
            checked += 1
    assert checked > len(tri) // 2


def test_batch_matches_single_and_float64():
    rng = np.random.default_rng(4)
    src = np.concatenate([face_points(rng), border_anchors((W, H))])
    dsts = np.stack([src + np.pad(rng.normal(0, 2, (20, 2)), ((0, 16), (0, 0))) for _ in range(3)])
    tri = triangulate(src)
    img = to_tensor(smooth_image()).double()
    batch = warp_images(img, torch.from_numpy(src)[None].expand(3, -1, -1), torch.from_numpy(dsts), tri)
    assert batch.shape == (3, 3, H, W) and batch.dtype == torch.float64
    single = warp_images(img, torch.from_numpy(src)[None], torch.from_numpy(dsts[2])[None], tri)
    torch.testing.assert_close(batch[2:], single)


def test_cpu_remap_matches_grid_sample_for_every_padding():
    """The CPU path (cv2.remap) against the grid_sample path (taken for tensors needing gradients)."""
    rng = np.random.default_rng(5)
    src = np.concatenate([face_points(rng), border_anchors((W, H))])
    dst = np.stack([src + np.pad(rng.normal(0, 3, (20, 2)), ((0, 16), (0, 0))) + [4.0, -3.0] for _ in range(2)])
    tri = triangulate(src)
    img = torch.from_numpy(np.concatenate([smooth_image(), smooth_image()[..., :1]], -1)).permute(2, 0, 1)[None]
    for padding in ("border", "zeros", "reflection"):
        args = (torch.from_numpy(src)[None].expand(2, -1, -1), torch.from_numpy(dst), tri)
        fast = warp_images(img, *args, padding_mode=padding, size=(W - 6, H + 4))
        reference = warp_images(img.clone().requires_grad_(), *args, padding_mode=padding, size=(W - 6, H + 4)).detach()
        assert fast.shape == reference.shape == (2, 4, H + 4, W - 6), padding
        assert float((fast - reference).abs().max()) < 5e-3, padding  # 1/32 px fixed-point weights
    alpha = warp_images(img[:, 3:], torch.from_numpy(src)[None], torch.from_numpy(dst[:1]), tri)
    torch.testing.assert_close(alpha, warp_images(img, torch.from_numpy(src)[None], torch.from_numpy(dst[:1]), tri)[:, 3:])


def per_triangle_backward_map(src: np.ndarray, dst: np.ndarray, tri: np.ndarray, index: np.ndarray) -> np.ndarray:
    """(H, W, 2) float64: each pixel's covering triangle's dst -> src affine from cv2.getAffineTransform
    (identity where ``index`` is -1), an implementation independent of the warp module's."""
    ys, xs = np.mgrid[0 : index.shape[0], 0 : index.shape[1]].astype(np.float64)
    out = np.stack([xs, ys], -1)
    for k in np.unique(index[index >= 0]):
        M = cv2.getAffineTransform(dst[tri[k]].astype(np.float32), src[tri[k]].astype(np.float32)).astype(np.float64)
        at = index == k
        out[at] = np.stack([xs[at], ys[at], np.ones(at.sum())], 1) @ M.T
    return out


def test_backward_map_equals_per_triangle_affines_and_marks_uncovered_pixels():
    rng = np.random.default_rng(6)
    src = np.concatenate([face_points(rng), border_anchors((W, H))])
    dst = src + np.pad(rng.normal(0, 2, (20, 2)), ((0, 16), (0, 0))) + [3.0, -2.0]  # anchors moved: a border strip uncovered
    tri = triangulate(src)
    index = triangle_index_map(dst, tri, (W, H))
    assert (index < 0).any() and (index >= 0).mean() > 0.9
    expected = per_triangle_backward_map(src, dst, tri, index)
    s, d = torch.from_numpy(src)[None], torch.from_numpy(dst)[None]
    grid, covered = backward_map(s, d, tri, (W, H), dtype=torch.float64)
    np.testing.assert_array_equal(covered[0].numpy(), index >= 0)
    np.testing.assert_allclose(grid[0].numpy(), expected, atol=1e-4)  # float32 affines of cv2.getAffineTransform's input
    grid32, _ = backward_map(s, d, tri, (W, H))
    assert grid32.dtype == torch.float32
    np.testing.assert_allclose(grid32[0].numpy(), expected, atol=1e-3)


def test_triangle_index_map_fills_given_array_with_the_uncovered_value():
    rng = np.random.default_rng(7)
    pts = face_points(rng)
    tri = triangulate(pts)
    fresh = triangle_index_map(pts, tri, (W, H))
    out = np.full((H, W), 123, np.int32)
    got = triangle_index_map(pts, tri, (W, H), uncovered=len(tri), out=out)
    assert got is out
    np.testing.assert_array_equal(got, np.where(fresh < 0, len(tri), fresh))
    with pytest.raises(ValueError, match="int32"):
        triangle_index_map(pts, tri, (W, H), out=np.zeros((H, W), np.int64))


def test_warp_in_buffers_equals_fresh_memory_and_reuses_it():
    rng = np.random.default_rng(8)
    src = np.concatenate([face_points(rng), border_anchors((W, H))])
    tri = triangulate(src)
    img = to_tensor(np.concatenate([smooth_image(), smooth_image()[..., :1]], -1))
    buffers = Buffers()
    outs = []
    for _ in range(2):
        dst = torch.from_numpy(src + np.pad(rng.normal(0, 2, (20, 2)), ((0, 16), (0, 0))))[None]
        fresh = warp_images(img, torch.from_numpy(src)[None], dst, tri)
        reused = warp_images(img, torch.from_numpy(src)[None], dst, tri, buffers=buffers)
        assert torch.equal(reused, fresh)
        outs.append(reused)
    assert outs[0].data_ptr() == outs[1].data_ptr()  # the second warp wrote into the first one's memory
