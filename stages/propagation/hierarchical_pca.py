"""Offline half of motion propagation: hierarchical PCA of the captured geometries (Sec. 10, 14).

For every feature point set F of the layout's hierarchy (1 set at level 0, 4 at level 1, 16 at
level 2 in the paper), the displacement vectors of F's points relative to the neutral geometry,
one per captured expression, are analysed by principal components; the affine subspace
``mean + span(components)`` is the set's *expression subspace*, the space of its "common" motions
onto which Proj(dV, F) of Sec. 10.1 projects.

The model is a plain bundle of arrays (``pca_model`` port type, stored as ``.npz`` without
pickle), so the runner can cache it like any stage output. Sets of different sizes are stored
concatenated, with offsets:

=========================  ================  ===================================================
key                        shape / dtype     meaning
=========================  ================  ===================================================
``neutral``                ``(N, 2) f8``     neutral geometry, px
``point_names``            ``(N,) str``      feature point names ("" when unknown)
``set_names``              ``(S,) str``      feature point set names
``set_levels``             ``(S,) i8``       hierarchy of each set (0 = whole face)
``set_offsets``            ``(S + 1,) i8``   set s owns rows ``set_offsets[s]:set_offsets[s+1]``
``set_points``             ``(M,) i8``       point index of each row (M = sum of set sizes)
``mean``                   ``(M, 2) f8``     mean displacement of each row's point over the
                                             captured expressions, px
``components``             ``(M, 2, C) f8``  principal directions: for set s, rows of s
                                             reshaped to ``(2 P_s, C)`` are orthonormal columns
                                             (x, y interleaved per point); columns past
                                             ``n_components[s]`` are zero
``n_components``           ``(S,) i8``       number of kept components per set
``explained_variance``     ``(S, C) f8``     fraction of the set's variance per kept component
=========================  ================  ===================================================
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Protocol, Sequence

import numpy as np


BUNDLE_KEYS = (
    "neutral",
    "point_names",
    "set_names",
    "set_levels",
    "set_offsets",
    "set_points",
    "mean",
    "components",
    "n_components",
    "explained_variance",
)


class FeaturePointSetLike(Protocol):
    """What training needs of a feature point set (``stages.layout.FeaturePointSet`` fits)."""

    name: str
    level: int
    points: Sequence[int]


@dataclass(frozen=True)
class HierarchicalPCA:
    """The hierarchical PCA model of Sec. 10, one expression subspace per feature point set.

    Attributes
    ----------
    neutral : (N, 2) float64
        Neutral geometry, px.
    point_names : tuple of str
        N feature point names ("" when unknown).
    set_names : tuple of str
        S feature point set names.
    levels : (S,) int64
        Hierarchy of each set: 0 (global), 1 (facial feature regions), 2 (details).
    points : tuple of (P_s,) int64 arrays
        Point indices of each set.
    means : tuple of (2 P_s,) float64 arrays
        Mean displacement of each set over the captured expressions, px, x/y interleaved.
    components : tuple of (2 P_s, C_s) float64 arrays
        Orthonormal principal directions of each set.
    explained_variance : tuple of (C_s,) float64 arrays
        Fraction of the set's displacement variance carried by each kept component.
    """

    neutral: np.ndarray
    point_names: tuple[str, ...]
    set_names: tuple[str, ...]
    levels: np.ndarray
    points: tuple[np.ndarray, ...]
    means: tuple[np.ndarray, ...]
    components: tuple[np.ndarray, ...]
    explained_variance: tuple[np.ndarray, ...]

    @property
    def n_points(self) -> int:
        return int(self.neutral.shape[0])

    @property
    def n_sets(self) -> int:
        return len(self.points)

    def overlaps(self) -> np.ndarray:
        """(S, S) bool: whether two feature point sets share at least one point."""
        member = np.zeros((self.n_sets, self.n_points), dtype=bool)
        for s, pts in enumerate(self.points):
            member[s, pts] = True
        shared = member.astype(np.int64) @ member.T.astype(np.int64)
        return shared > 0

    def to_bundle(self) -> dict[str, np.ndarray]:
        """The model as a ``pca_model`` bundle (see the module docstring for the keys)."""
        sizes = np.array([len(p) for p in self.points], dtype=np.int64)
        n_kept = np.array([c.shape[1] for c in self.components], dtype=np.int64)
        width = max(1, int(n_kept.max()))
        rows = int(sizes.sum())
        components = np.zeros((rows, 2, width))
        explained = np.zeros((self.n_sets, width))
        offsets = np.concatenate([[0], np.cumsum(sizes)])
        for s, (u, ratio) in enumerate(zip(self.components, self.explained_variance)):
            components[offsets[s] : offsets[s + 1], :, : u.shape[1]] = u.reshape(sizes[s], 2, u.shape[1])
            explained[s, : ratio.size] = ratio
        return {
            "neutral": np.asarray(self.neutral, dtype=np.float64),
            "point_names": np.array(self.point_names, dtype=str),
            "set_names": np.array(self.set_names, dtype=str),
            "set_levels": self.levels.astype(np.int64),
            "set_offsets": offsets.astype(np.int64),
            "set_points": np.concatenate(self.points).astype(np.int64),
            "mean": np.concatenate(self.means).reshape(rows, 2),
            "components": components,
            "n_components": n_kept,
            "explained_variance": explained,
        }

    @classmethod
    def from_bundle(cls, bundle: Mapping[str, np.ndarray], *, source: str = "pca_model") -> "HierarchicalPCA":
        """Read a ``pca_model`` bundle; a missing or inconsistent field raises ValueError naming it."""
        missing = [k for k in BUNDLE_KEYS if k not in bundle]
        if missing:
            raise ValueError(f"{source}: missing field(s) {', '.join(missing)} (not a pca_model bundle)")
        neutral = np.asarray(bundle["neutral"], dtype=np.float64)
        offsets = np.asarray(bundle["set_offsets"], dtype=np.int64)
        set_points = np.asarray(bundle["set_points"], dtype=np.int64)
        n_kept = np.asarray(bundle["n_components"], dtype=np.int64)
        levels = np.asarray(bundle["set_levels"], dtype=np.int64)
        mean = np.asarray(bundle["mean"], dtype=np.float64)
        components = np.asarray(bundle["components"], dtype=np.float64)
        explained = np.asarray(bundle["explained_variance"], dtype=np.float64)
        n_sets = levels.size
        if neutral.ndim != 2 or neutral.shape[1] != 2:
            raise ValueError(f"{source}: field 'neutral' must be (N, 2), got {neutral.shape}")
        if offsets.shape != (n_sets + 1,) or offsets[0] != 0 or offsets[-1] != set_points.size:
            raise ValueError(f"{source}: field 'set_offsets' does not match 'set_levels'/'set_points'")
        if set_points.size and (set_points.min() < 0 or set_points.max() >= neutral.shape[0]):
            raise ValueError(f"{source}: field 'set_points' has indices outside 0..{neutral.shape[0] - 1}")
        if mean.shape != (set_points.size, 2) or components.shape[:2] != (set_points.size, 2):
            raise ValueError(f"{source}: fields 'mean'/'components' do not match 'set_points'")
        if n_kept.shape != (n_sets,) or (n_kept > components.shape[2]).any():
            raise ValueError(f"{source}: field 'n_components' does not match 'components'")
        spans = list(zip(offsets[:-1], offsets[1:]))
        return cls(
            neutral=neutral,
            point_names=tuple(str(n) for n in bundle["point_names"]),
            set_names=tuple(str(n) for n in bundle["set_names"]),
            levels=levels,
            points=tuple(set_points[a:b] for a, b in spans),
            means=tuple(mean[a:b].reshape(-1) for a, b in spans),
            components=tuple(components[a:b, :, :c].reshape(2 * (b - a), c) for (a, b), c in zip(spans, n_kept)),
            explained_variance=tuple(explained[s, :c] for s, c in enumerate(n_kept)),
        )


def fit_hierarchical_pca(
    neutral: np.ndarray,
    captured: np.ndarray,
    feature_point_sets: Sequence[FeaturePointSetLike],
    *,
    n_components: int = 8,
    variance_kept: float = 1.0,
    point_names: Sequence[str] | None = None,
) -> HierarchicalPCA:
    """Hierarchical PCA of captured expressions (Sec. 10: one PCA per feature point set).

    For each set F the displacement vectors ``captured[k, F] - neutral[F]`` (flattened to
    ``2 |F|`` values, x/y interleaved) of the K captured expressions are centred on their mean
    and decomposed by SVD; the leading principal directions are kept.

    Parameters
    ----------
    neutral : (N, 2) float
        Neutral geometry, px.
    captured : (K, N, 2) float
        Captured expression geometries in the neutral's frame, px (30-40 in the paper, Sec. 14).
    feature_point_sets : sequence of S objects with ``name``, ``level`` and ``points``
        The layout's hierarchy (``Layout.feature_point_sets``).
    n_components : int
        Most principal components kept per set (the paper keeps 5-10, Sec. 14). Never more
        than the rank of the set's centred data.
    variance_kept : float in (0, 1]
        Also stop at the fewest components whose explained variance reaches this fraction;
        1.0 keeps ``n_components``.
    point_names : sequence of N str, optional
        Stored in the model so that inputs can be checked against it.

    Returns
    -------
    HierarchicalPCA

    Raises
    ------
    ValueError
        Shapes that disagree, fewer than 2 captured geometries, non-finite coordinates,
        ``n_components < 1``, ``variance_kept`` outside (0, 1], a bad feature point set.
    """
    neutral = np.asarray(neutral, dtype=np.float64)
    captured = np.asarray(captured, dtype=np.float64)
    if neutral.ndim != 2 or neutral.shape[1] != 2:
        raise ValueError(f"neutral geometry must be (N, 2), got {neutral.shape}")
    n_points = neutral.shape[0]
    if captured.ndim != 3 or captured.shape[1:] != neutral.shape:
        raise ValueError(f"captured geometries must be (K, {n_points}, 2), got {captured.shape}")
    if captured.shape[0] < 2:
        raise ValueError(f"PCA needs at least 2 captured geometries, got {captured.shape[0]}")
    if not np.isfinite(captured).all() or not np.isfinite(neutral).all():
        raise ValueError("captured/neutral geometries contain NaN or infinite coordinates")
    if n_components < 1:
        raise ValueError(f"n_components must be >= 1, got {n_components}")
    if not 0.0 < variance_kept <= 1.0:
        raise ValueError(f"variance_kept must be in (0, 1], got {variance_kept}")
    if not feature_point_sets:
        raise ValueError("the layout has no feature point sets")
    names = tuple(point_names) if point_names is not None else ("",) * n_points
    if len(names) != n_points:
        raise ValueError(f"point_names has {len(names)} names for {n_points} points")

    displacement = captured - neutral[None]
    points, means, components, explained = [], [], [], []
    for fps in feature_point_sets:
        idx = np.asarray(fps.points, dtype=np.int64)
        if idx.size == 0 or idx.min() < 0 or idx.max() >= n_points or np.unique(idx).size != idx.size:
            raise ValueError(f"feature point set '{fps.name}': indices must be distinct, in 0..{n_points - 1}")
        x = displacement[:, idx].reshape(captured.shape[0], -1)
        mu = x.mean(axis=0)
        _, sing, vt = np.linalg.svd(x - mu, full_matrices=False)
        var = sing**2
        total = var.sum()
        ratio = var / total if total > 0 else np.zeros_like(var)
        rank = int((sing > sing[0] * 1e-9).sum()) if total > 0 else 0
        keep = min(n_components, rank)
        if variance_kept < 1.0:
            keep = min(keep, int(np.searchsorted(np.cumsum(ratio), variance_kept)) + 1)
        points.append(idx)
        means.append(mu)
        components.append(vt[:keep].T.copy())
        explained.append(ratio[:keep])
    return HierarchicalPCA(
        neutral=neutral,
        point_names=names,
        set_names=tuple(str(f.name) for f in feature_point_sets),
        levels=np.array([int(f.level) for f in feature_point_sets], dtype=np.int64),
        points=tuple(points),
        means=tuple(means),
        components=tuple(components),
        explained_variance=tuple(explained),
    )
