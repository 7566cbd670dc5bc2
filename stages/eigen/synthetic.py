"""Training renders of the performer's face model (Valente & Dugelay, "Synthesis of facial
expressions": the realistic face model rendered under sampled animation vectors V = (P, mu)).

The realistic face model here is the fixture generator's face (``scripts/facegen``) of the
performer's identity, which a fixture pack names in its ``generator`` entry, rendered with the
pack's camera; the animation parameters are the generator's 12 expression controls. A pack made
from photos of a real performer has no generator: synthesizing its expressions from the pack
(e.g. by warping and blending its examples) is not implemented, and :func:`performer_rig` says so.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Callable, Iterable, Iterator

import numpy as np

from stages.eigen.model import EigenModel, fit_eigen_model, fit_geometry_map
from stages.eigen.patches import feature_windows
from stages.geometry.compensate import fit_similarity
from stages.layout import load_layout, read_yaml

CHECKOUT = Path(__file__).resolve().parents[2]  # holds scripts/facegen in a source checkout


def generator() -> tuple[ModuleType, ModuleType, ModuleType]:
    """The generator's modules ``(face, render, make_fixtures)``. In a source checkout whose root
    is not on ``sys.path`` (the ``runner`` console script) the root is added; ValueError when the
    generator is not there."""
    if importlib.util.find_spec("scripts") is None:
        if not (CHECKOUT / "scripts" / "facegen" / "render.py").is_file():
            raise ValueError("expected the face generator scripts/facegen beside the stages package, got none")
        sys.path.append(str(CHECKOUT))
    return (importlib.import_module("scripts.facegen.face"), importlib.import_module("scripts.facegen.render"),
            importlib.import_module("scripts.make_fixtures"))


@dataclass
class PerformerRig:
    """The performer's face model posed like the pack's images: the generator's face, camera,
    reference pose ``R0 (3, 3)``, ``t0 (3,)`` mm, texture resolution and the neck pivot (mm) the
    clips turn the head about."""

    face: object
    camera: object
    R0: np.ndarray
    t0: np.ndarray
    ppm: float
    pivot: np.ndarray
    param_names: tuple[str, ...]

    def pose(self, angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``R, t`` of the head turned by (yaw, pitch, roll) deg about the pivot from the reference."""
        _, render, _ = generator()
        R = render.rotation(*angles) @ self.R0
        return R, self.t0 + self.R0 @ self.pivot - R @ self.pivot

    def points(self, controls: np.ndarray, angles: np.ndarray | None = None) -> np.ndarray:
        """Exact projections ``(N, 2)`` px of the layout points (no rendering)."""
        face_mod, render, _ = generator()
        R, t = self.pose(np.zeros(3) if angles is None else angles)
        p3 = face_mod.expression_points3d(self.face.neutral, controls, self.face.layout)
        return render.project(p3, R, t, self.camera.A)[0]

    def render(self, controls: np.ndarray, angles: np.ndarray, *, supersample: int = 2) -> tuple[np.ndarray, np.ndarray]:
        """Image ``(H, W, 3)`` uint8 and points ``(N, 2)`` px of one animation vector."""
        face_mod, render, _ = generator()
        R, t = self.pose(angles)
        p3 = face_mod.expression_points3d(self.face.neutral, controls, self.face.layout)
        out = render.render(self.face, p3, R, t, self.camera, supersample=supersample, ppm=self.ppm)
        return out.image, out.points


def performer_rig(pack_dir: Path) -> PerformerRig:
    """The face model of a fixture pack's performer (``pack.yaml: generator.identity_seed`` and
    the pose and camera of ``generator.truth``); ValueError naming the field for other packs."""
    manifest = read_yaml(Path(pack_dir) / "pack.yaml", what="actor pack", noun="manifest")
    gen = manifest.get("generator") if isinstance(manifest, dict) else None
    if not isinstance(gen, dict) or "identity_seed" not in gen or "truth" not in gen:
        raise ValueError(f"{pack_dir}/pack.yaml: field 'generator': expected the generator's identity_seed and truth "
                         "(the eigenfeature training renders a face model; pack-driven synthesis of a real performer "
                         "is not implemented), got none")
    face_mod, render, fixtures = generator()
    truth = np.load(Path(pack_dir) / str(gen["truth"]), allow_pickle=False)
    size = tuple(int(v) for v in manifest["image_size"])
    camera = render.Camera(np.asarray(truth["intrinsics"], dtype=np.float64), size)
    face = render.make_face(int(gen["identity_seed"]), load_layout(manifest.get("layout", "zhang134")))
    t0 = np.asarray(truth["t"], dtype=np.float64)
    return PerformerRig(face, camera, np.asarray(truth["R"], dtype=np.float64), t0, render.texture_ppm(camera, t0[2]),
                        np.asarray(fixtures.NECK_PIVOT, dtype=np.float64), tuple(face_mod.CONTROLS))


def training_samples(rig: PerformerRig, controls: np.ndarray, angles: np.ndarray, *, supersample: int = 2,
                     progress: Callable[[int], None] = lambda n: None) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Render each sample: ``(image (H, W, 3) uint8, similarity (4,))`` with the similarity of its
    rigid points to the neutral's (the paper's "known feature locations and pose")."""
    rigid = list(rig.face.layout.rigid)
    neutral = rig.points(np.zeros(len(rig.param_names)))
    for c, a in zip(controls, angles):
        image, points = rig.render(c, a, supersample=supersample)
        yield image, fit_similarity(neutral[rigid], points[rigid])
        progress(1)


def train_on_renders(rig: PerformerRig, controls: np.ndarray, angles: np.ndarray, *, q: int, margin: float = 0.25,
                     step: float = 1.0, supersample: int = 2, blur_px: float = 0.0, normalize: bool = False,
                     min_inside: float = 0.98, samples: Iterable[tuple[np.ndarray, np.ndarray]] | None = None,
                     progress: Callable[[int], None] = lambda n: None) -> EigenModel:
    """Render every sample (or take ``samples``, the renders of :func:`training_samples` made
    before), cut its patches and fit the model.

    Parameters
    ----------
    controls : (m, C)
        Animation parameters per sample (:mod:`.sampling`).
    angles : (m, 3)
        (yaw, pitch, roll) deg per sample.
    q, margin, step, blur_px, normalize, min_inside
        Eigenfeatures per feature, the patch windows (:func:`.patches.feature_windows`) and their
        conditioning (:func:`.patches.patch_vectors`).
    supersample : int
        The generator's antialiasing (the fixture clips use 2).
    """
    layout = rig.face.layout
    neutral = rig.points(np.zeros(len(rig.param_names)))
    windows = feature_windows(neutral, layout.point_names, margin=margin, step=step)
    if samples is None:
        samples = training_samples(rig, controls, angles, supersample=supersample, progress=progress)
    geometry = fit_geometry_map(controls, np.stack([rig.points(c) for c in controls]))
    return fit_eigen_model(samples, angles, controls, windows=windows, neutral=neutral,
                           point_names=layout.point_names, param_names=rig.param_names, geometry=geometry, q=q,
                           blur_px=blur_px, normalize=normalize, min_inside=min_inside)
