"""One frame of Sec. 14.1: the target mesh, textured with the synthesized expression image, rendered.

Colour is rasterized in scene-linear light (the sRGB texture is decoded first, so MSAA coverage
and bilinear texture filtering average light, not code values) and comes back as premultiplied
linear RGBA, the EXR convention of ``write.exr``; :func:`to_display` re-encodes it to sRGB over
black for video.
"""

from __future__ import annotations

import numpy as np

from stages.color import linear_to_srgb, srgb_to_linear, to_unit_float
from stages.render3d.raster import MeshRenderer

__all__ = ["render_textured", "to_display", "scaled_intrinsics"]


def render_textured(
    renderer: MeshRenderer,
    vertices: np.ndarray,
    triangles: np.ndarray,
    uv: np.ndarray,
    texture: np.ndarray,
    A: np.ndarray,
    *,
    mask: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Render a mesh textured with an sRGB image.

    Parameters
    ----------
    renderer : the output size's renderer
    vertices : (V, 3) float, camera frame mm
    triangles : (F, 3) int, counter-clockwise on screen
    uv : (V, 2) float, texture px (x right, y down, origin at the top-left pixel's centre)
    texture : (h, w, 3) float in [0, 1] sRGB-encoded, or uint8
    A : (3, 3) float, intrinsics of the output image, px
    mask : (h, w) or (h, w, 1) float in [0, 1], optional
        The texture's alpha (the synthesized face mask); opaque when omitted.

    Returns
    -------
    rgba : (H, W, 4) float32, premultiplied scene-linear RGBA (alpha = coverage x mask)
    depth : (H, W) float32, camera depth of the surface, mm (``inf`` where empty)
    """
    linear = srgb_to_linear(to_unit_float(np.asarray(texture)).astype(np.float32))
    if mask is not None:
        alpha = np.asarray(mask, np.float32).reshape(linear.shape[:2] + (1,))
        linear = np.concatenate([linear, alpha], axis=2)
    return renderer.render(vertices, triangles, uv, linear, A)


def to_display(rgba: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Premultiplied linear RGBA ``(..., 4)`` -> sRGB over black ``(..., 3)`` and alpha ``(..., 1)``, float32."""
    rgba = np.asarray(rgba, np.float32)
    return np.clip(linear_to_srgb(np.clip(rgba[..., :3], 0.0, None)), 0.0, 1.0), rgba[..., 3:]


def scaled_intrinsics(A: np.ndarray, scale: float) -> np.ndarray:
    """Intrinsics ``(3, 3)`` of the same camera for an image ``scale`` times larger.

    Pixel centres map as ``u' = scale (u + 0.5) - 0.5`` (origin at the top-left pixel's centre).
    """
    S = np.array([[scale, 0.0, 0.5 * scale - 0.5], [0.0, scale, 0.5 * scale - 0.5], [0.0, 0.0, 1.0]])
    return S @ np.asarray(A, np.float64)
