"""The editor's models and renderer: a target pack's hierarchical PCA and synthesis model.

Both models are made exactly as the pipeline makes them (``pack.load``'s bundles into
``propagate.train`` and ``synthesis.build`` with their default parameters), so an edit renders as
the pipeline renders the exported keyframes.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from stages.geometry.points_file import MAX_POINT_VALUES
from editor.preview import PreviewSynthesizer
from stages.propagation.pinned import PinnedPropagation
from runner.stage import Context, SequenceStage, StageError
from stages.actor_pack import load_pack
from stages.pack.bundles import pack_to_bundles
from stages.layout import Layout
from stages.npz_file import read_npz
from stages.propagation.hierarchical_pca import HierarchicalPCA
from stages.propagation.stage import TrainHierarchicalPCA
from stages.synthesis.build import BuildSynthesis
from stages.synthesis.synthesize import Synthesizer

log = logging.getLogger("editor")


def pack_models(pack: Path, *, device: str = "cpu") -> tuple[Layout, HierarchicalPCA, dict[str, np.ndarray]]:
    """A target pack's layout, hierarchical PCA and synthesis model, made as the pipeline makes
    them: ``pack.load``'s bundles into ``propagate.train`` and ``synthesis.build``, each with
    its default parameters."""
    loaded = load_pack(pack)
    bundles = pack_to_bundles(loaded)

    def run(stage: type[SequenceStage]) -> dict[str, Any]:
        def no_files(port: str) -> Path:
            raise StageError(f"{stage.name}: the editor gives no folder for files output '{port}'")

        ctx = Context(device=device, files_dir=no_files, log=log)
        inputs = {port: bundles[port] for port in stage.inputs}
        return stage().run(inputs, {p.name: p.default for p in stage.params}, ctx)

    pca = HierarchicalPCA.from_bundle(run(TrainHierarchicalPCA)["pca_model"])
    return loaded.layout, pca, run(BuildSynthesis)["model"]


def to_uint8(rgb: torch.Tensor) -> np.ndarray:
    """8-bit images of a batch of synthesized images.

    Parameters
    ----------
    rgb : (B, 3, H, W) float tensor, sRGB, nominally in [0, 1] (values outside are clamped)

    Returns
    -------
    (B, H, W, 3) uint8, BGR (OpenCV's channel order), ``floor(255 v + 0.5)`` clamped to 0..255:
    rounded to nearest, halves up.
    """
    levels = torch.mul(rgb, 255.0).add_(0.5).clamp_(0, 255).to(torch.uint8).cpu().numpy()  # (B, 3, H, W)
    return np.stack([cv2.merge([image[2], image[1], image[0]]) for image in levels])


def encode(image: np.ndarray, *, mime: str, jpeg_quality: int = 90) -> bytes:
    """Bytes of one image in a format browsers decode.

    Parameters
    ----------
    image : (H, W, 3) uint8, BGR
    mime : ``"image/jpeg"`` (quality ``jpeg_quality``, 1..100) or ``"image/png"`` (lossless,
        zlib level 1: the fastest)
    """
    if mime == "image/jpeg":
        ok, buffer = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    elif mime == "image/png":
        ok, buffer = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    else:
        raise ValueError(f"mime must be 'image/jpeg' or 'image/png', got {mime!r}")
    if not ok:
        raise RuntimeError(f"cv2.imencode failed to encode {mime}")
    return buffer.tobytes()


def read_performance(path: Path, layout: Layout) -> np.ndarray:
    """The target geometry per frame of a run's ``data.npz`` (``target_xy``), to touch up.

    Returns
    -------
    (T, N, 2) float64, px, in the target neutral's frame.

    Raises
    ------
    ValueError
        The file is not a readable ``.npz`` (:class:`stages.npz_file.NpzError`: empty,
        truncated, an array of more than :data:`stages.geometry.points_file.MAX_POINT_VALUES` values), has
        no ``target_xy`` of the layout's shape, its names differ from the layout's, or it holds
        non-finite values (the message names the file and the field).
    """
    data = read_npz(path, ("target_xy", "target_names"), max_values=MAX_POINT_VALUES)
    if "target_xy" not in data:
        raise ValueError(f"{path}: field 'target_xy' is missing (a run's data/data.npz has it)")
    xy = np.asarray(data["target_xy"], np.float64)
    names = tuple(str(n) for n in data["target_names"]) if "target_names" in data else layout.point_names
    if xy.ndim != 3 or xy.shape[1:] != (layout.n_points, 2) or len(xy) == 0:
        raise ValueError(f"{path}: field 'target_xy' is {xy.shape}, the pack's layout needs (T, {layout.n_points}, 2)")
    if names != layout.point_names:
        raise ValueError(f"{path}: field 'target_names' differs from the pack's layout {layout.name!r}")
    if not np.isfinite(xy).all():
        raise ValueError(f"{path}: field 'target_xy' has non-finite values")
    return xy


@dataclass(frozen=True)
class Rendered:
    """Encoded images with what making them cost.

    Attributes
    ----------
    images : list of bytes, one per geometry
    types : list of str, their MIME types (``image/jpeg`` or ``image/png``)
    wall_s, cpu_s : float
        Wall-clock and CPU seconds of the calling thread that synthesis and encoding took (the
        CPU time is all of it with one torch thread, and hardly grows when other processes load
        the machine).
    """

    images: list[bytes]
    types: list[str]
    wall_s: float
    cpu_s: float


class EditorEngine:
    """A target pack's models, ready to propagate edits and synthesize images.

    Parameters
    ----------
    pack : Path
        The target's actor pack.
    device : str
        Torch device of the synthesis.
    jpeg_quality : int
        Quality of the JPEG images sent to the page (previews and in-betweens), 1..100.
    preview_scale : float
        Size of the images shown while dragging, as a fraction of the pack's image size, in
        (0, 1] (see :meth:`preview`; 1: the pack's size).
    performance : Path, optional
        A run's ``data.npz`` whose frames can be loaded and touched up.
    """

    def __init__(
        self,
        pack: Path,
        *,
        device: str = "cpu",
        jpeg_quality: int = 90,
        preview_scale: float = 1.0,
        performance: Path | None = None,
    ) -> None:
        if not 1 <= int(jpeg_quality) <= 100:
            raise ValueError(f"jpeg_quality must be in 1..100, got {jpeg_quality}")
        self.layout, self.pca, self.model = pack_models(pack, device=device)
        self.propagation = PinnedPropagation(self.pca)
        self.synthesizer = Synthesizer(self.model, device=device)
        self.size = tuple(int(v) for v in self.model["size"])  # (W, H)
        self.previewer = PreviewSynthesizer(self.synthesizer, self.model, scale=preview_scale)
        self.jpeg_quality = int(jpeg_quality)
        self.performance = None if performance is None else read_performance(performance, self.layout)

    def render(self, points: np.ndarray, *, lossless_last: bool = False) -> Rendered:
        """The pipeline's synthesis (:meth:`stages.synthesis.synthesize.Synthesizer.render`,
        full mode, default parameters) of geometries ``points (B, N, 2)`` px, at the pack's
        size, as JPEG images; the last one PNG (lossless) with ``lossless_last``."""
        wall, cpu = time.perf_counter(), time.thread_time()
        with torch.inference_mode():  # no autograd bookkeeping on the QP's many small operations
            rgb, _, _ = self.synthesizer.render(points)
            images = to_uint8(rgb)
        types = ["image/jpeg"] * len(images)
        if lossless_last:
            types[-1] = "image/png"
        data = [encode(image, mime=mime, jpeg_quality=self.jpeg_quality) for image, mime in zip(images, types)]
        return Rendered(data, types, time.perf_counter() - wall, time.thread_time() - cpu)

    def preview(self, points: np.ndarray) -> Rendered:
        """The image shown while dragging: the synthesis at ``preview_scale`` of the pack's size
        (:class:`editor.preview.PreviewSynthesizer`), as one JPEG; with ``preview_scale`` 1 (the
        default) it is :meth:`render`'s image before JPEG (to float32 rounding).

        Parameters
        ----------
        points : (N, 2) float, px, at the pack's size
        """
        wall, cpu = time.perf_counter(), time.thread_time()
        with torch.inference_mode():
            (image,) = to_uint8(self.previewer.render(points))
        data = encode(image, mime="image/jpeg", jpeg_quality=self.jpeg_quality)
        return Rendered([data], ["image/jpeg"], time.perf_counter() - wall, time.thread_time() - cpu)

    def description(self) -> dict[str, Any]:
        """What the page needs to draw and edit: image size, point names, the neutral, the
        subregion outlines (point indices) and the number of loadable performance frames."""
        return {
            "size": list(self.size),
            "names": list(self.layout.point_names),
            "neutral": self.pca.neutral.tolist(),
            "subregions": [{"name": s.name, "polygon": list(s.polygon)} for s in self.layout.subregions],
            "performance_frames": 0 if self.performance is None else len(self.performance),
        }
