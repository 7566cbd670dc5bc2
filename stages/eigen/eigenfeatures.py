"""Eigenfeatures: PCA of one feature's training patches (Valente & Dugelay, "Visual modeling of
facial expressions": I ~ D_mean + (e_1 | ... | e_q) alpha = D_mean + E alpha)."""

from __future__ import annotations

import numpy as np


def fit_eigenfeatures(patches: np.ndarray, *, q: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean and the first ``q`` principal directions of a feature's training patches.

    Parameters
    ----------
    patches : (m, n) float
        ``m`` training patches of one feature, each flattened to ``n`` pixels.
    q : int
        Eigenfeatures kept, ``1 <= q <= min(m, n)``.

    Returns
    -------
    mean : (n,) float32
        ``D_mean``, the mean patch.
    basis : (n, q) float32
        ``E``, orthonormal columns (the eigenfeatures), by decreasing variance.
    """
    D = np.asarray(patches, dtype=np.float64)
    if D.ndim != 2:
        raise ValueError(f"expected patches (m, n), got shape {D.shape}")
    if not 1 <= q <= min(D.shape):
        raise ValueError(f"expected 1 <= q <= min(m, n) = {min(D.shape)}, got q={q}")
    mean = D.mean(axis=0)
    _, _, vt = np.linalg.svd(D - mean, full_matrices=False)
    return mean.astype(np.float32), vt[:q].T.astype(np.float32)


def eigen_scores(patches: np.ndarray, mean: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """Scores ``alpha = E^T (I - D_mean)`` ``(..., q)`` float64 of patches ``(..., n)`` (the
    paper's correlation with the eigenfeatures; ``E`` has orthonormal columns)."""
    patches = np.asarray(patches, dtype=np.float64)
    if patches.shape[-1] != mean.shape[0] or basis.shape[0] != mean.shape[0]:
        raise ValueError(f"expected patches of {mean.shape[0]} pixels, got shape {patches.shape}")
    return (patches - mean) @ basis.astype(np.float64)
