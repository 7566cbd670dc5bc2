"""The eigenfeature model of a performer and its use on frames (Valente & Dugelay).

Training (:func:`fit_eigen_model`): per feature the eigenfeatures of its patches
(:mod:`.eigenfeatures`), the observations ``lambda = (r_x, r_y, r_z, alpha_{1,1}, ..., alpha_{q,p},
1)`` of every training render and the normal equations of the estimator ``L`` (:mod:`.estimator`),
plus a linear map from the animation parameters to the neutral-frame geometry of all layout
points (the generator's point motion, least squares over the training parameters).

Analysis (:func:`analyze_frames`): patches through the frame's similarity, scores, ``mu = L
lambda``, clipped to the parameters' range [0, 1]; a feature whose patch leaves the image is
masked and ``L`` is solved without its rows (:func:`.estimator.solve_estimator`). The similarity
comes with the frames or is fitted from the frame's points (:func:`similarities_from_points`: the
model's rigid points, neutral -> frame, as in training).
Geometry (:func:`parameters_to_points`): ``x = x_0 + sum_k mu_k B_k`` in the neutral's frame,
then the frame's similarity. Parameters are clipped to the range the training sampled
(``param_low``, ``param_high``: [0, 1] for the generator's controls, +-2 standard deviations for
a pack's PCA parameters).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np

from stages.eigen.eigenfeatures import eigen_scores, fit_eigenfeatures
from stages.eigen.estimator import normal_equations, solve_estimator
from stages.eigen.patches import FeatureWindow, patch_vectors
from stages.geometry.compensate import fit_similarity
from stages.geometry.similarity import apply_similarity

ROTATION_ROWS = 3  # (r_x, r_y, r_z) = (pitch, yaw, roll) deg, first in lambda


@dataclass(frozen=True)
class EigenModel:
    """A trained eigenfeature model; arrays as in :meth:`to_bundle` (N points, C parameters,
    p features, q eigenfeatures each, d = 3 + p q + 1 observation rows)."""

    point_names: tuple[str, ...]
    param_names: tuple[str, ...]
    neutral: np.ndarray  # (N, 2) px, the frame the patches are cut in
    rigid: tuple[int, ...]  # points the similarity neutral -> frame is fitted on
    param_low: np.ndarray  # (C,) the sampled range, estimates are clipped to it
    param_high: np.ndarray  # (C,)
    windows: tuple[FeatureWindow, ...]
    means: tuple[np.ndarray, ...]  # p x (n_j,) float32
    bases: tuple[np.ndarray, ...]  # p x (n_j, q) float32
    gram: np.ndarray  # (d, d)
    cross: np.ndarray  # (C, d)
    rms: np.ndarray  # (d,)
    count: int
    geometry_base: np.ndarray  # (N, 2) px
    geometry_basis: np.ndarray  # (C, N, 2) px per unit parameter
    min_inside: float
    blur_px: float
    normalize: bool

    def vectors(self, image: np.ndarray, similarity: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
        """The frame's patch vectors and validity (:func:`.patches.patch_vectors`)."""
        return patch_vectors(
            image, similarity, self.windows, blur_px=self.blur_px, normalize=self.normalize, min_inside=self.min_inside
        )

    @property
    def q(self) -> int:
        return int(self.bases[0].shape[1])

    @property
    def n_rows(self) -> int:
        return ROTATION_ROWS + len(self.windows) * self.q + 1

    def rows(self, feature_valid: np.ndarray, *, rotation: bool) -> np.ndarray:
        """Observation rows used with the given features ``(p,)`` bool, with or without rotation."""
        q = self.q
        rows = list(range(ROTATION_ROWS)) if rotation else []
        for j, ok in enumerate(feature_valid):
            if ok:
                rows += range(ROTATION_ROWS + j * q, ROTATION_ROWS + (j + 1) * q)
        return np.array(rows + [self.n_rows - 1], dtype=np.int64)

    def estimator(self, feature_valid: np.ndarray, *, rotation: bool = True, ridge: float = 0.0) -> np.ndarray:
        """``L`` ``(C, |S|)`` over :meth:`rows`."""
        return solve_estimator(
            self.gram,
            self.cross,
            self.rms,
            count=self.count,
            ridge=ridge,
            rows=self.rows(feature_valid, rotation=rotation),
            intercept=self.n_rows - 1,
        )

    def to_bundle(self) -> dict[str, np.ndarray]:
        """Arrays only (npz without pickle): names, neutral, per-feature windows and the
        concatenated means ``(sum n_j,)`` / bases ``(sum n_j, q)``, estimator and geometry terms."""
        membership = np.zeros((len(self.windows), len(self.point_names)), dtype=bool)
        for j, w in enumerate(self.windows):
            membership[j, list(w.points)] = True
        return {
            "point_names": np.array(self.point_names, dtype=str),
            "param_names": np.array(self.param_names, dtype=str),
            "feature_names": np.array([w.name for w in self.windows], dtype=str),
            "feature_points": membership,
            "feature_origin": np.array([w.origin for w in self.windows], dtype=np.float64),
            "feature_step": np.array([w.step for w in self.windows], dtype=np.float64),
            "feature_shape": np.array([w.shape for w in self.windows], dtype=np.int64),
            "neutral": self.neutral,
            "rigid": np.array(self.rigid, dtype=np.int64),
            "param_low": self.param_low,
            "param_high": self.param_high,
            "mean": np.concatenate(self.means),
            "basis": np.concatenate(self.bases),
            "gram": self.gram,
            "cross": self.cross,
            "rms": self.rms,
            "count": np.array(self.count),
            "geometry_base": self.geometry_base,
            "geometry_basis": self.geometry_basis,
            "min_inside": np.array(self.min_inside),
            "blur_px": np.array(self.blur_px),
            "normalize": np.array(self.normalize),
        }

    @classmethod
    def from_bundle(cls, bundle: dict[str, np.ndarray]) -> "EigenModel":
        """Inverse of :meth:`to_bundle`; ValueError naming a missing or inconsistent key."""
        keys = (
            "point_names",
            "param_names",
            "feature_names",
            "feature_points",
            "feature_origin",
            "feature_step",
            "feature_shape",
            "neutral",
            "rigid",
            "param_low",
            "param_high",
            "mean",
            "basis",
            "gram",
            "cross",
            "rms",
            "count",
            "geometry_base",
            "geometry_basis",
            "min_inside",
            "blur_px",
            "normalize",
        )
        missing = [k for k in keys if k not in bundle]
        if missing:
            raise ValueError(f"eigen model: expected keys {missing}, got none of them")
        shapes = np.asarray(bundle["feature_shape"], dtype=np.int64)
        windows = tuple(
            FeatureWindow(
                str(name),
                tuple(int(i) for i in np.flatnonzero(member)),
                (float(o[0]), float(o[1])),
                float(step),
                (int(s[0]), int(s[1])),
            )
            for name, member, o, step, s in zip(
                bundle["feature_names"], bundle["feature_points"], bundle["feature_origin"], bundle["feature_step"], shapes
            )
        )
        sizes = shapes.prod(axis=1)
        mean, basis = np.asarray(bundle["mean"]), np.asarray(bundle["basis"])
        if mean.shape[0] != sizes.sum() or basis.shape[0] != sizes.sum():
            raise ValueError(
                f"eigen model: expected {sizes.sum()} patch pixels in 'mean' and 'basis', "
                f"got {mean.shape[0]} and {basis.shape[0]}"
            )
        cuts = np.cumsum(sizes)[:-1]
        model = cls(
            tuple(str(n) for n in bundle["point_names"]),
            tuple(str(n) for n in bundle["param_names"]),
            np.asarray(bundle["neutral"], dtype=np.float64),
            tuple(int(i) for i in bundle["rigid"]),
            np.asarray(bundle["param_low"], dtype=np.float64),
            np.asarray(bundle["param_high"], dtype=np.float64),
            windows,
            tuple(np.split(mean, cuts)),
            tuple(np.split(basis, cuts)),
            np.asarray(bundle["gram"]),
            np.asarray(bundle["cross"]),
            np.asarray(bundle["rms"]),
            int(bundle["count"]),
            np.asarray(bundle["geometry_base"]),
            np.asarray(bundle["geometry_basis"]),
            float(bundle["min_inside"]),
            float(bundle["blur_px"]),
            bool(bundle["normalize"]),
        )
        if model.gram.shape != (model.n_rows, model.n_rows) or model.cross.shape != (len(model.param_names), model.n_rows):
            raise ValueError(
                f"eigen model: expected gram ({model.n_rows}, {model.n_rows}) and cross "
                f"({len(model.param_names)}, {model.n_rows}), got {model.gram.shape} and {model.cross.shape}"
            )
        return model


def observation(angles: np.ndarray, scores: list[np.ndarray]) -> np.ndarray:
    """``lambda = (r_x, r_y, r_z, alpha_1, ..., alpha_p, 1)`` ``(d,)`` from angles ``(3,)`` (yaw,
    pitch, roll) deg and per-feature scores ``p x (q,)``."""
    yaw, pitch, roll = np.asarray(angles, dtype=np.float64)
    return np.concatenate([[pitch, yaw, roll], *scores, [1.0]])


def fit_geometry_map(parameters: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares linear map from parameters ``(m, C)`` to geometries ``(m, N, 2)`` px:
    ``x = base + sum_k mu_k basis_k``; returns ``base (N, 2)``, ``basis (C, N, 2)``."""
    mu = np.asarray(parameters, dtype=np.float64)
    pts = np.asarray(points, dtype=np.float64)
    if mu.ndim != 2 or pts.ndim != 3 or pts.shape[0] != mu.shape[0]:
        raise ValueError(f"expected parameters (m, C) and points (m, N, 2), got {mu.shape} and {pts.shape}")
    design = np.column_stack([np.ones(len(mu)), mu])
    coef = np.linalg.lstsq(design, pts.reshape(len(mu), -1), rcond=None)[0]
    return coef[0].reshape(pts.shape[1:]), coef[1:].reshape(mu.shape[1], *pts.shape[1:])


def fit_eigen_model(
    samples: Iterable[tuple[np.ndarray, np.ndarray]],
    angles: np.ndarray,
    parameters: np.ndarray,
    *,
    windows: tuple[FeatureWindow, ...],
    neutral: np.ndarray,
    point_names: tuple[str, ...],
    param_names: tuple[str, ...],
    rigid: tuple[int, ...],
    param_range: tuple[np.ndarray, np.ndarray],
    geometry: tuple[np.ndarray, np.ndarray],
    q: int,
    blur_px: float = 0.0,
    normalize: bool = False,
    min_inside: float = 0.98,
) -> EigenModel:
    """Train the model from rendered samples.

    Parameters
    ----------
    samples : iterable of m (image (H, W, 3) uint8, similarity (4,))
        Each training render and the similarity mapping the neutral onto it (known feature
        locations); its patches are the datasets ``D_{i,j}``.
    angles : (m, 3)
        Head rotation of each sample, (yaw, pitch, roll) deg relative to the neutral's pose.
    parameters : (m, C)
        Animation parameters of each sample.
    windows, neutral, point_names, param_names
        Feature windows (:func:`.patches.feature_windows`), neutral ``(N, 2)`` px and names.
    rigid : tuple of int
        Points the similarities neutral -> frame are fitted on (the samples' and at run time).
    param_range : (low (C,), high (C,))
        The sampled range of the parameters; estimates are clipped to it.
    geometry : (base (N, 2), basis (C, N, 2))
        From :func:`fit_geometry_map`.
    q : int
        Eigenfeatures per feature.
    blur_px, normalize, min_inside
        Patch conditioning (:func:`.patches.patch_vectors`), kept in the model for the analysis.
    """
    patches: list[list[np.ndarray]] = [[] for _ in windows]
    for image, similarity in samples:
        vectors, ok = patch_vectors(image, similarity, windows, blur_px=blur_px, normalize=normalize, min_inside=min_inside)
        if not ok.all():
            raise ValueError(
                f"expected every training patch inside the image, got features "
                f"{[w.name for w, v in zip(windows, ok) if not v]} outside in sample {len(patches[0])}"
            )
        for j, v in enumerate(vectors):
            patches[j].append(v)
    if len(patches[0]) != len(angles):
        raise ValueError(f"expected {len(angles)} samples (one per angle row), got {len(patches[0])}")
    D = [np.stack(P) for P in patches]
    fitted = [fit_eigenfeatures(d, q=q) for d in D]
    scores = [eigen_scores(d, mean, basis) for d, (mean, basis) in zip(D, fitted)]
    lam = np.stack([observation(angles[i], [s[i] for s in scores]) for i in range(len(angles))])
    gram, cross, rms = normal_equations(lam, parameters)
    low, high = (np.broadcast_to(np.asarray(v, dtype=np.float64), (len(param_names),)).copy() for v in param_range)
    return EigenModel(
        tuple(point_names),
        tuple(param_names),
        np.asarray(neutral, dtype=np.float64),
        tuple(int(i) for i in rigid),
        low,
        high,
        tuple(windows),
        tuple(m for m, _ in fitted),
        tuple(b for _, b in fitted),
        gram,
        cross,
        rms,
        len(lam),
        np.asarray(geometry[0], dtype=np.float64),
        np.asarray(geometry[1], dtype=np.float64),
        float(min_inside),
        float(blur_px),
        bool(normalize),
    )


def frame_scores(model: EigenModel, image: np.ndarray, similarity: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """Per-feature scores ``p x (q,)`` of one frame and which features are inside it ``(p,)``."""
    vectors, valid = model.vectors(image, similarity)
    return [eigen_scores(v, m, b) for v, m, b in zip(vectors, model.means, model.bases)], valid


def analyze_frames(
    model: EigenModel,
    frames: Iterable[np.ndarray],
    similarity: np.ndarray,
    valid: np.ndarray,
    angles: np.ndarray | None,
    *,
    ridge: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Animation parameters of each frame.

    Parameters
    ----------
    frames : iterable of T (H, W, 3) uint8
        RGB frames.
    similarity : (T, 4)
        ``(a, b, tx, ty)`` neutral -> frame (eq. 8).
    valid : (T,) bool
        Frames whose similarity (and rotation) can be used.
    angles : (T, 3) or None
        Head rotation (yaw, pitch, roll) deg; None: the estimator without rotation rows.
    ridge : float
        Ridge of the estimator (0: the paper's least squares).

    Returns
    -------
    parameters : (T, C) float64
        In the model's ``[param_low, param_high]``; NaN where no feature could be read.
    feature_valid : (T, p) bool
    """
    similarity = np.asarray(similarity, dtype=np.float64)
    T = len(similarity)
    params = np.full((T, len(model.param_names)), np.nan)
    feature_valid = np.zeros((T, len(model.windows)), dtype=bool)
    estimators: dict[tuple[bool, ...], np.ndarray] = {}
    for t, image in enumerate(frames):
        if t >= T:
            raise ValueError(f"expected {T} frames (one per similarity), got more")
        if not valid[t]:
            continue
        scores, ok = frame_scores(model, image, similarity[t])
        feature_valid[t] = ok
        if not ok.any():
            continue
        key = tuple(bool(v) for v in ok)
        if key not in estimators:
            estimators[key] = model.estimator(ok, rotation=angles is not None, ridge=ridge)
        lam = observation(np.zeros(3) if angles is None else angles[t], scores)
        params[t] = np.clip(estimators[key] @ lam[model.rows(ok, rotation=angles is not None)], model.param_low, model.param_high)
    return params, feature_valid


def similarities_from_points(model: EigenModel, xy: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Similarities ``(T, 4)`` mapping the model's neutral onto each frame's points (least squares
    over the model's rigid points, eq. 8; the "known feature locations" of the paper) and which
    frames have all of them ``(T,)`` bool.

    Parameters
    ----------
    xy : (T, N, 2) float
        The frame's layout points, px, in the model's point order.
    valid : (T, N) bool
    """
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 3 or xy.shape[1:] != model.neutral.shape:
        raise ValueError(f"expected points (T, {len(model.neutral)}, 2), got {xy.shape}")
    rigid = list(model.rigid)
    ok = np.asarray(valid, dtype=bool)[:, rigid].all(axis=1) & np.isfinite(xy[:, rigid]).all(axis=(1, 2))
    sims = np.tile([1.0, 0.0, 0.0, 0.0], (len(xy), 1))
    for t in np.flatnonzero(ok):
        sims[t] = fit_similarity(model.neutral[rigid], xy[t, rigid])
    return sims, ok


def parameters_to_points(model: EigenModel, parameters: np.ndarray, similarity: np.ndarray | None = None) -> np.ndarray:
    """Geometry ``(T, N, 2)`` px of all layout points: ``x_0 + sum_k mu_k B_k`` in the neutral's
    frame, mapped by each frame's similarity ``(T, 4)`` when given. NaN parameters give NaN."""
    mu = np.asarray(parameters, dtype=np.float64)
    xy = model.geometry_base[None] + np.einsum("tc,cnk->tnk", mu, model.geometry_basis)
    if similarity is None:
        return xy
    return np.stack([apply_similarity(s, p) for s, p in zip(np.asarray(similarity, dtype=np.float64), xy)])
