"""Optical-flow refinement of the examples' alignment (Sec. 15 remedy for "crawling" pixels).

The triangulation warp (Sec. 5.2) puts every example's feature points on the standard geometry,
but texture between the points (brow hairs, lid creases, teeth edges) lands a pixel or two off
from one example to the next, and blending them (eq. 6) blurs it. The paper's remedy: refine the
alignment by optical flow. Each geometrically aligned example ``I_i`` is resampled as

    I'_i(x) = I_i(x + f_i(x)),        f_i = flow from the reference R to I_i,

(so that ``R(x) ~ I_i(x + f_i(x))``), the dense flow computed by DIS (Kroeger et al. 2016,
``cv2.DISOpticalFlow``) on the grey images, its variational refinement smoothing the field so
that expression changes (wrinkles) stay in the example instead of being "explained" by motion.
The flow is clipped to ``max_px`` per component: the geometric warp already did the coarse work.

The reference for the face examples is the neutral image aligned to the standard geometry (the
texture ``warp-only`` mode shows), for the teeth examples the standard image (mouth open widest).
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from stages.color import luma_opencv

__all__ = ["dis_flow", "apply_flow", "refine_alignment", "refine_model"]


def dis_flow(
    reference: np.ndarray, image: np.ndarray, *, patch_px: int = 8, stride_px: int = 4, smoothness: float = 20.0
) -> np.ndarray:
    """Dense flow from ``reference`` to ``image`` by DIS (``cv2.DISOpticalFlow``, preset MEDIUM).

    Parameters
    ----------
    reference, image : (H, W, 3) uint8 RGB
    patch_px, stride_px : int
        DIS patch size and patch stride, px.
    smoothness : float
        Weight of the smoothness term of the variational refinement (OpenCV's ``alpha``).

    Returns
    -------
    (H, W, 2) float32, px: ``reference(x, y) ~ image(x + f_x, y + f_y)``.
    """
    import cv2

    if reference.shape != image.shape or reference.ndim != 3 or reference.dtype != np.uint8 or image.dtype != np.uint8:
        raise ValueError(
            f"reference and image must be (H, W, 3) uint8 of one shape, got {reference.shape} {reference.dtype} and {image.shape} {image.dtype}"
        )
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    dis.setPatchSize(int(patch_px))
    dis.setPatchStride(int(stride_px))
    dis.setVariationalRefinementAlpha(float(smoothness))
    return dis.calc(luma_opencv(reference), luma_opencv(image), None)


def apply_flow(image: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """``out(x) = image(x + flow(x))``, bilinear, border replicated (pixel-centre convention).

    Parameters
    ----------
    image : (H, W, C) uint8 or float
    flow : (H, W, 2) float, px

    Returns
    -------
    (H, W, C) of ``image``'s dtype (uint8 rounded).
    """
    import cv2

    H, W = image.shape[:2]
    if flow.shape != (H, W, 2):
        raise ValueError(f"flow must be (H, W, 2) = ({H}, {W}, 2), got {flow.shape}")
    gx, gy = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    return cv2.remap(
        image,
        gx + flow[..., 0].astype(np.float32),
        gy + flow[..., 1].astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )


def refine_alignment(images: np.ndarray, reference: np.ndarray, *, max_px: float = 3.0, **dis: float) -> np.ndarray:
    """Resample each geometrically aligned image by its flow to ``reference`` (clipped to ``max_px``).

    Parameters
    ----------
    images : (M, H, W, 3) uint8, aligned to the standard geometry
    reference : (H, W, 3) uint8
    max_px : float
        Per-component bound on the flow, px.
    **dis
        Options of :func:`dis_flow`.

    Returns
    -------
    (M, H, W, 3) uint8.
    """
    return (
        np.stack([apply_flow(im, np.clip(dis_flow(reference, im, **dis), -max_px, max_px)) for im in images])
        if len(images)
        else images.copy()
    )


def refine_model(model: Mapping[str, np.ndarray], *, max_px: float, **dis: float) -> dict[str, np.ndarray]:
    """A ``synthesis_model`` bundle whose ``examples`` and ``teeth`` are refined by flow.

    The face examples are aligned to the neutral image warped to the standard geometry, the teeth
    examples to the standard image (see the module docstring); the other keys are shared.
    ``max_px`` <= 0 returns the model unchanged (as a dict).
    """
    from stages.synthesis.build import align_to_standard

    if max_px <= 0:
        return dict(model)
    neutral = align_to_standard(
        np.asarray(model["neutral"])[None],
        np.asarray(model["neutral_points"])[None],
        model["standard_points"],
        model["anchors"],
        model["triangles"],
    )[0]
    return {
        **model,
        "examples": refine_alignment(np.asarray(model["examples"]), neutral, max_px=max_px, **dis),
        "teeth": refine_alignment(np.asarray(model["teeth"]), np.asarray(model["standard"]), max_px=max_px, **dis),
    }
