"""The image shown while a point is dragged: the pipeline's synthesis, made cheaper per update.

It runs the pipeline's synthesis (Sec. 6-8: the same per-subregion QP coefficients, eq. 2-5,
compositing with the fade bands, eq. 6-7, and the final warp of Sec. 7) with two savings that
leave the image as it is:

* **compositing on the face box only**, as the pipeline's compositor does it
  (:func:`stages.synthesis.composite.prepare_compositor`: outside the bounding box of the face
  labels the composite is the standard image whatever the coefficients);
* **no alpha.** Only the three colour channels are warped (the editor never shows the face
  alpha), and they are clamped to [0, 1] in place.

At ``scale`` < 1 (``--preview-scale``) the same runs on a model whose images and weight maps are
reduced to ``(w, h) = round(s (W, H))``: compositing and warping cost about ``s^2`` of the full
size's, and the JPEG is about ``s^2`` of the bytes for the browser to decode. Positions map
between the sizes with pixel centres at integers (OpenCV): ``x' = (x + 0.5) w / W - 0.5``,
``y' = (y + 0.5) h / H - 0.5``.
"""

from __future__ import annotations

from typing import Mapping

import cv2
import numpy as np
import torch

from stages.synthesis.composite import Compositor, composite, prepare_compositor
from stages.synthesis.synthesize import Synthesizer
from stages.synthesis.warp import warp_images

__all__ = ["preview_size", "to_preview", "reduced_model", "PreviewSynthesizer"]


def preview_size(size: tuple[int, int], scale: float) -> tuple[int, int]:
    """``(w, h)`` of a preview of ``size (W, H)`` at ``scale`` in (0, 1], at least 1 px each."""
    if not 0 < scale <= 1:
        raise ValueError(f"preview scale must be in (0, 1], got {scale}")
    return tuple(max(1, round(v * scale)) for v in size)


def to_preview(points: np.ndarray, size: tuple[int, int], small: tuple[int, int]) -> np.ndarray:
    """Positions ``points (..., 2)`` px in an image of ``size (W, H)`` -> the same positions in
    one of ``small (w, h)`` (pixel centres at integers)."""
    scale = np.asarray(small, np.float64) / np.asarray(size, np.float64)
    return (np.asarray(points, np.float64) + 0.5) * scale - 0.5


def reduced_model(model: Mapping[str, np.ndarray], small: tuple[int, int]) -> dict[str, np.ndarray]:
    """The compositing fields of a ``synthesis_model`` bundle at ``small (w, h)``.

    Images (``examples``, ``teeth``, ``standard``, ``outside``) and the fade weight ``blend_r`` are
    area-averaged; the subregion labels ``blend_i1``, ``blend_i2`` are sampled at the nearest
    pixel. The other fields are the model's (point fields stay at the full size).
    """
    w, h = small

    def area(image: np.ndarray) -> np.ndarray:
        return cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)

    def nearest(labels: np.ndarray) -> np.ndarray:
        return cv2.resize(labels.astype(np.int32), (w, h), interpolation=cv2.INTER_NEAREST).astype(labels.dtype)

    reduced = dict(model)
    for key in ("examples", "teeth"):
        stack = np.asarray(model[key])
        reduced[key] = np.stack([area(image) for image in stack]) if len(stack) else np.zeros((0, h, w, 3), np.uint8)
    for key in ("standard", "outside"):
        reduced[key] = area(np.asarray(model[key]))
    reduced["blend_r"] = area(np.asarray(model["blend_r"], np.float32))
    reduced["blend_i1"] = nearest(np.asarray(model["blend_i1"]))
    reduced["blend_i2"] = nearest(np.asarray(model["blend_i2"]))
    reduced["size"] = np.array([w, h], np.int64)
    return reduced


class PreviewSynthesizer:
    """Synthesis of one geometry while dragging (module docstring), at the full size or a reduced
    one, sharing a :class:`Synthesizer`'s QPs, anchors and triangulation.

    Parameters
    ----------
    synthesizer : Synthesizer
        The pipeline's synthesis of the model (its QPs, anchors and triangulation are used).
    model : dict of arrays
        The ``synthesis_model`` bundle ``synthesizer`` was made from.
    scale : float
        Image size / full size, in (0, 1] (1: the pack's size).

    Raises
    ------
    ValueError
        ``scale`` out of range; the synthesizer blends band-pass details (the reduced model's
        compositor is made without them, so the sizes would not show the same image).
    """

    def __init__(self, synthesizer: Synthesizer, model: Mapping[str, np.ndarray], *, scale: float) -> None:
        if synthesizer.compositor.details is not None:
            raise ValueError("the drag image composites without band-pass blending (detail_power 1, the pipeline's default)")
        self.synthesizer = synthesizer
        self.full_size = tuple(int(v) for v in model["size"])
        self.size = preview_size(self.full_size, scale)
        self.compositor: Compositor = (
            synthesizer.compositor
            if self.size == self.full_size
            else prepare_compositor(
                reduced_model(model, self.size), device=synthesizer.device, teeth_power=synthesizer.compositor.teeth_power
            )
        )
        standard = np.concatenate([model["standard_points"], synthesizer.anchors])
        self.standard_points = torch.from_numpy(to_preview(standard, self.full_size, self.size)).to(synthesizer.device)

    def render(self, points: np.ndarray) -> torch.Tensor:
        """The image of one geometry.

        Parameters
        ----------
        points : (N, 2) float, px at the full size

        Returns
        -------
        (1, 3, h, w) float32 sRGB in [0, 1]; at scale 1 it is :meth:`Synthesizer.render`'s
        ``rgb`` (to float32 rounding).
        """
        synth = self.synthesizer
        points = np.asarray(points, np.float64)
        dst = to_preview(np.concatenate([points, synth.anchors]), self.full_size, self.size)
        coeffs, _ = synth.qp.coefficients(points[None])
        standard = composite(self.compositor, coeffs, teeth_mix=synth.teeth_mix(points[None]))[:, :3]
        dst_t = torch.from_numpy(dst[None]).to(synth.device)
        return warp_images(standard, self.standard_points[None], dst_t, synth.triangles, size=self.size).clamp_(0, 1)
