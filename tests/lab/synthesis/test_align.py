"""Optical-flow refinement: the resampling against scipy, and DIS recovering known shifts."""

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter, map_coordinates

from lab.synthesis.align import apply_flow, dis_flow, refine_alignment


def textured(seed: int = 0, size: tuple[int, int] = (96, 128)) -> np.ndarray:
    """(H, W, 3) uint8: band-limited random texture (blobs of a few px, full contrast)."""
    noise = np.random.default_rng(seed).normal(size=size + (3,))
    t = gaussian_filter(noise, (2.0, 2.0, 0))
    return np.clip(128 + 60 * t / t.std(), 0, 255).round().astype(np.uint8)


def test_apply_flow_matches_map_coordinates():
    image = textured().astype(np.float32)
    H, W = image.shape[:2]
    rng = np.random.default_rng(1)
    flow = rng.uniform(-2, 2, (H, W, 2)).astype(np.float32)
    out = apply_flow(image, flow)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    ref = np.stack(
        [map_coordinates(image[..., c], [yy + flow[..., 1], xx + flow[..., 0]], order=1, mode="nearest") for c in range(3)], -1
    )
    np.testing.assert_allclose(out[4:-4, 4:-4], ref[4:-4, 4:-4], atol=0.02)
    with pytest.raises(ValueError, match="flow"):
        apply_flow(image, flow[:-1])


@pytest.mark.parametrize("shift", [(1.5, -0.75), (2.0, 1.0), (-0.4, 0.3)])
def test_dis_recovers_a_known_shift_and_refinement_undoes_it(shift):
    reference = textured()
    H, W = reference.shape[:2]
    moved = apply_flow(reference, np.broadcast_to(np.array(shift, np.float32), (H, W, 2)).copy())  # moved(x) = ref(x + s)
    flow = dis_flow(reference, moved)
    inner = (slice(12, -12), slice(12, -12))
    np.testing.assert_allclose(np.median(flow[inner].reshape(-1, 2), 0), -np.array(shift), atol=0.1)
    before = np.abs(moved.astype(float) - reference)[inner].mean()
    after = np.abs(refine_alignment(moved[None], reference, max_px=3.0)[0].astype(float) - reference)[inner].mean()
    assert after < 0.5 * before  # what remains is the blur of two bilinear resamplings
    clipped = refine_alignment(moved[None], reference, max_px=0.1)[0]
    assert np.abs(clipped.astype(float) - reference)[inner].mean() > 0.5 * before  # the bound holds the flow back
