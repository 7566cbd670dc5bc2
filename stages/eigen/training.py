"""Training an eigenfeature model from renders of a face model (Valente & Dugelay, "Synthesis of
facial expressions": the realistic face model rendered under sampled animation vectors V = (P, mu),
then patches, eigenfeatures and the linear estimator).

One implementation for every face model; only the face model differs (:class:`FaceModel`): the
fixture generator's face (:mod:`.synthetic`, the parameters are its 12 expression controls) or a
real performer's actor pack driven by the example-based synthesis (:mod:`.packface`, the
parameters are the PCA of the pack's captured geometries).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterable, Iterator, Protocol

import numpy as np

from stages.eigen.model import EigenModel, fit_eigen_model, fit_geometry_map
from stages.eigen.patches import feature_windows
from stages.geometry.compensate import fit_similarity
from stages.layout import read_yaml


class FaceModel(Protocol):
    """A performer's face model: geometry and images under animation parameters and rotations.

    ``param_names`` (C,), ``point_names`` (N,), ``rigid`` (the points the similarities are fitted
    on), ``param_range`` (low (C,), high (C,)): the range sampled; :meth:`points` the geometry
    ``(N, 2)`` px of parameters ``(C,)`` in the neutral pose (no rendering);
    :meth:`render_batch` images ``(B, H, W, 3)`` uint8 RGB and their points ``(B, N, 2)`` px of
    parameters ``(B, C)`` under (yaw, pitch, roll) deg ``(B, 3)``; :meth:`sampling` the training
    set of a sampling kind.
    """

    param_names: tuple[str, ...]
    point_names: tuple[str, ...]
    rigid: tuple[int, ...]
    param_range: tuple[np.ndarray, np.ndarray]

    def points(self, params: np.ndarray) -> np.ndarray: ...

    def render_batch(self, params: np.ndarray, angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...

    def sampling(self, kind: str, *, samples: int, seed: int) -> tuple[np.ndarray, np.ndarray]: ...


def face_model(pack_dir: Path, *, supersample: int = 2, variance: float = 0.95, max_params: int = 8) -> FaceModel:
    """The face model of a performer pack: the generator's face for a fixture pack (``pack.yaml``
    has a ``generator`` entry; ``supersample`` its antialiasing), else the pack itself driven by
    the example-based synthesis (``variance``, ``max_params``: :func:`.packface.pca_parameters`)."""
    manifest = read_yaml(Path(pack_dir) / "pack.yaml", what="actor pack", noun="manifest")
    if isinstance(manifest, dict) and "generator" in manifest:
        from stages.eigen.synthetic import performer_rig

        return performer_rig(Path(pack_dir), supersample=supersample)
    from stages.actor_pack import load_pack
    from stages.eigen.packface import PackFace

    return PackFace(load_pack(pack_dir), variance=variance, max_params=max_params)


def training_samples(
    face: FaceModel, params: np.ndarray, angles: np.ndarray, *, batch: int = 8, progress: Callable[[int], None] = lambda n: None
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Render each sample (``batch`` at a time): ``(image (H, W, 3) uint8, similarity (4,))`` with
    the similarity of its rigid points to the neutral's (the paper's "known feature locations
    and pose")."""
    rigid = list(face.rigid)
    neutral = face.points(np.zeros(len(face.param_names)))
    for start in range(0, len(params), batch):
        images, points = face.render_batch(params[start : start + batch], angles[start : start + batch])
        for image, pts in zip(images, points):
            yield image, fit_similarity(neutral[rigid], pts[rigid])
        progress(len(images))


def train_on_renders(
    face: FaceModel,
    params: np.ndarray,
    angles: np.ndarray,
    *,
    q: int,
    margin: float = 0.25,
    step: float = 1.0,
    blur_px: float = 0.0,
    normalize: bool = False,
    min_inside: float = 0.98,
    samples: Iterable[tuple[np.ndarray, np.ndarray]] | None = None,
    progress: Callable[[int], None] = lambda n: None,
) -> EigenModel:
    """Render every sample (or take ``samples``, the renders of :func:`training_samples` made
    before), cut its patches and fit the model.

    Parameters
    ----------
    face : FaceModel
    params : (m, C)
        Animation parameters per sample (:meth:`FaceModel.sampling`).
    angles : (m, 3)
        (yaw, pitch, roll) deg per sample.
    q, margin, step, blur_px, normalize, min_inside
        Eigenfeatures per feature, the patch windows (:func:`.patches.feature_windows`) and their
        conditioning (:func:`.patches.patch_vectors`).
    """
    neutral = face.points(np.zeros(len(face.param_names)))
    windows = feature_windows(neutral, face.point_names, margin=margin, step=step)
    if samples is None:
        samples = training_samples(face, params, angles, progress=progress)
    geometry = fit_geometry_map(params, np.stack([face.points(p) for p in params]))
    return fit_eigen_model(
        samples,
        angles,
        params,
        windows=windows,
        neutral=neutral,
        point_names=face.point_names,
        param_names=face.param_names,
        rigid=face.rigid,
        param_range=face.param_range,
        geometry=geometry,
        q=q,
        blur_px=blur_px,
        normalize=normalize,
        min_inside=min_inside,
    )
