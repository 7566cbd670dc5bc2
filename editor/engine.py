"""The editor's models and renderer: a target pack's hierarchical PCA and synthesis model.

Both models are made exactly as the pipeline makes them (``propagate.train`` and
``synthesis.build`` run with their default parameters), so an edit renders as the pipeline
renders the exported keyframes.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Mapping

import cv2
import numpy as np
import torch

from runner.stage import Context, SequenceStage, StageError
from stages.actor_pack import load_pack
from stages.layout import Layout
from stages.propagation.hierarchical_pca import HierarchicalPCA
from stages.propagation.stage import TrainHierarchicalPCA
from stages.synthesis.build import BuildSynthesis
from stages.synthesis.synthesize import Synthesizer

log = logging.getLogger("editor")


def _run_default(stage: type[SequenceStage], pack: Path, *, device: str) -> dict[str, Any]:
    """Run a pack stage with its default parameters, as a pipeline would."""

    def no_files(port: str) -> Path:
        raise StageError(f"{stage.name}: the editor gives no folder for files output '{port}'")

    ctx = Context(device=device, files_dir=no_files, log=log)
    return stage().run({"pack": pack}, {p.name: p.default for p in stage.params}, ctx)


def encode_jpeg(rgb: torch.Tensor, *, quality: int) -> list[bytes]:
    """JPEG bytes of a batch of images.

    Parameters
    ----------
    rgb : (B, 3, H, W) float tensor, sRGB in [0, 1]
    quality : int, 1..100 (OpenCV's ``IMWRITE_JPEG_QUALITY``)
    """
    images = (rgb * 255.0 + 0.5).clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()
    out = []
    for image in images:
        ok, buffer = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:
            raise RuntimeError("cv2.imencode failed to encode a JPEG")
        out.append(buffer.tobytes())
    return out


def read_performance(path: Path, layout: Layout) -> np.ndarray:
    """The target geometry per frame of a run's ``data.npz`` (``target_xy``), to touch up.

    Returns
    -------
    (T, N, 2) float64, px, in the target neutral's frame.

    Raises
    ------
    ValueError
        The file has no ``target_xy`` of the layout's shape, its names differ from the layout's,
        or it holds non-finite values (the message names the file and the field).
    """
    with np.load(path, allow_pickle=False) as data:
        if "target_xy" not in data.files:
            raise ValueError(f"{path}: field 'target_xy' is missing (a run's data/data.npz has it)")
        xy = np.asarray(data["target_xy"], np.float64)
        names = tuple(str(n) for n in data["target_names"]) if "target_names" in data.files else layout.point_names
    if xy.ndim != 3 or xy.shape[1:] != (layout.n_points, 2) or len(xy) == 0:
        raise ValueError(f"{path}: field 'target_xy' is {xy.shape}, the pack's layout needs (T, {layout.n_points}, 2)")
    if names != layout.point_names:
        raise ValueError(f"{path}: field 'target_names' differs from the pack's layout {layout.name!r}")
    if not np.isfinite(xy).all():
        raise ValueError(f"{path}: field 'target_xy' has non-finite values")
    return xy


class EditorEngine:
    """A target pack's models, ready to propagate edits and synthesize images.

    Parameters
    ----------
    pack : Path
        The target's actor pack.
    device : str
        Torch device of the synthesis.
    jpeg_quality : int
        Quality of the images sent to the page.
    performance : Path, optional
        A run's ``data.npz`` whose frames can be loaded and touched up.
    """

    def __init__(self, pack: Path, *, device: str = "cpu", jpeg_quality: int = 85, performance: Path | None = None) -> None:
        self.layout: Layout = load_pack(pack).layout
        self.pca = HierarchicalPCA.from_bundle(_run_default(TrainHierarchicalPCA, pack, device=device)["pca_model"])
        self.model: Mapping[str, np.ndarray] = _run_default(BuildSynthesis, pack, device=device)["model"]
        self.synthesizer = Synthesizer(self.model, device=device)
        self.size = tuple(int(v) for v in self.model["size"])  # (W, H)
        self.jpeg_quality = int(jpeg_quality)
        self.performance = None if performance is None else read_performance(performance, self.layout)

    def render(self, points: np.ndarray) -> tuple[list[bytes], float, float]:
        """JPEG images of geometries ``points (B, N, 2)`` px, with the wall-clock and the CPU
        seconds of the calling thread that synthesis and JPEG encoding took (the CPU time is
        all of it with one torch thread, and does not grow when other processes load the
        machine)."""
        wall, cpu = time.perf_counter(), time.thread_time()
        with torch.inference_mode():  # no autograd bookkeeping on the QP's many small operations
            rgb, _, _ = self.synthesizer.render(points)
            images = encode_jpeg(rgb, quality=self.jpeg_quality)
        return images, time.perf_counter() - wall, time.thread_time() - cpu

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
