"""Pixels that no real source image holds: their matte, and a plausible fill from the pixels around.

A *validity matte* ``V`` (H, W) in [0, 1] says how much of each pixel comes from a real source
image: 1 inside, 0 for a pixel the source does not show (beyond the footage's frame, a region a
turned head uncovers), fractions where a bilinear sample straddles the edge. Resampling an image
``I`` whose outside is 0 gives ``V * I`` (the colour premultiplied by the matte) and resampling
the indicator of the inside gives ``V``: a warp with ``cv2.BORDER_CONSTANT`` 0 of the image and
of a plane of ones yields both.

The fill is a push-pull pyramid (Gortler et al., "The Lumigraph", SIGGRAPH 1996, Sec. 3.4:
pull = average the premultiplied colour and the weight down a Gaussian pyramid; push = composite
each level *over* the level below upsampled, ``C_k = P_k + (1 - V_k) up(C_k+1)``). Each missing
pixel gets a smooth colour from the real pixels nearest to it, with no streak and no seam where
the matte ends. Its cost is two pyramid passes of the region's crop whatever the share missing,
where ``cv2.inpaint`` (Telea) spends per missing pixel; the two are compared against the truth,
and timed, by ``scripts/bench_shot.py`` (rows ``shot_fill_*``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["COARSEST_PX", "push_pull_fill", "fill_invalid", "fill_regions"]

COARSEST_PX = 4  # the pyramid stops when the smaller side is at most this
CONTEXT = 0.5  # a region is filled from a crop grown by this fraction of its larger side (and CONTEXT_PX)
CONTEXT_PX = 16


def push_pull_fill(premultiplied: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Push-pull interpolation of a matte-premultiplied image into the pixels the matte leaves out.

    Parameters
    ----------
    premultiplied : (H, W, 3) float32
        The colour times ``valid`` (0 where nothing is known).
    valid : (H, W) float32 in [0, 1]
        Validity matte.

    Returns
    -------
    (H, W, 4) float32: channels 0-2 ``premultiplied + (1 - valid) * up(C_1)``, the finest level of
    the push (module docstring), channel 3 ones; the colour itself where ``valid`` is 1, 0 where
    no pixel is valid.

    The levels are 4-channel (premultiplied colour, weight) images and the colour estimates carry
    a fourth channel (their weight, 1), so that each pass is one OpenCV call over contiguous
    memory: ``cv2.pyrDown`` / ``cv2.pyrUp``, and the over-composite ``C_k = P_k + (1 - V_k) U``
    as one ``cv2.accumulateProduct``.
    """
    import cv2

    H, W = valid.shape
    if premultiplied.shape != (H, W, 3):
        raise ValueError(f"premultiplied must be ({H}, {W}, 3), got {premultiplied.shape}")
    weight = np.clip(np.asarray(valid, np.float32), 0.0, 1.0)
    levels = [cv2.merge([np.asarray(premultiplied, np.float32), weight])]
    while min(levels[-1].shape[:2]) > COARSEST_PX:
        levels.append(cv2.pyrDown(levels[-1]))
    coarse = levels[-1]
    colour = np.divide(coarse, coarse[..., 3:], out=np.zeros_like(coarse), where=coarse[..., 3:] > 1e-6)
    for level in reversed(levels[:-1]):
        h, w = level.shape[:2]
        up = cv2.pyrUp(colour, dstsize=(w, h))
        colour = level.copy()
        cv2.accumulateProduct(up, cv2.merge([1.0 - level[..., 3]] * 4), colour)  # the level over the coarser estimate
    return colour


def fill_invalid(image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``valid * image + (1 - valid) * fill``: ``image`` where it is real, the push-pull fill where not.

    Parameters
    ----------
    image : (H, W, 3) float32 colour (not premultiplied; any values where ``valid`` is 0)
    valid : (H, W) float in [0, 1]

    Returns
    -------
    (H, W, 3) float32, a new array; equal to ``image`` where ``valid`` is 1.
    """
    import cv2

    valid = np.clip(np.asarray(valid, np.float32), 0.0, 1.0)
    premultiplied = cv2.multiply(np.asarray(image, np.float32), cv2.merge([valid] * 3))
    return cv2.cvtColor(push_pull_fill(premultiplied, valid), cv2.COLOR_RGBA2RGB)


def fill_regions(image: np.ndarray, valid: np.ndarray) -> int:
    """Fill, in place, the missing pixels of ``image (H, W, C >= 3) float32`` (its first three
    channels, any strides), region by region: each connected region (8-connected) of pixels less
    than half real (``valid (H, W)`` below 0.5) is filled by :func:`fill_invalid` on a crop around
    it grown by ``CONTEXT`` of its larger side and ``CONTEXT_PX`` (the real pixels there are its
    context; the crop's partly real pixels are blended by their validity), so a strip along the
    image's edge costs a thin crop, not the whole frame. A pixel at least half real outside every
    such crop (a sample reaching less than half a pixel beyond the source's edge) keeps its colour:
    what it misses is taken from the nearest real pixel, the source's edge. Returns the number of
    regions.
    """
    import cv2

    H, W = valid.shape
    holes = (valid < 0.5).astype(np.uint8)
    n, _, stats, _ = cv2.connectedComponentsWithStats(holes, connectivity=8)
    for x, y, w, h, _ in stats[1:]:
        grow = int(CONTEXT * max(w, h)) + CONTEXT_PX
        x0, y0, x1, y1 = max(x - grow, 0), max(y - grow, 0), min(x + w + grow, W), min(y + h + grow, H)
        crop = (slice(y0, y1), slice(x0, x1), slice(0, 3))
        image[crop] = fill_invalid(np.ascontiguousarray(image[crop]), valid[crop[:2]])
    return n - 1
