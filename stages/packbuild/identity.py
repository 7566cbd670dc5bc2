"""A coarse identity check for a folder of photos: a face-shape signature from the landmarker's
3D mesh that does not change with the head's position, size or rotation, and the photos whose
signature is far from the majority's.

The signature is the set of 3D distances between rigid points of MediaPipe's face mesh (eye
corners, nose bridge, nose tip and base, nostrils, face sides at the eyes' height, forehead),
divided by their mean: a similarity (translation, rotation, scale) of the head leaves it
unchanged, and expressions move these points little. It is a proportion test, not face
recognition: two people with similar proportions pass as one (docs/packbuild.md, "Photos").
"""

from __future__ import annotations

import numpy as np

# MediaPipe face-mesh vertices that an expression moves little (canonical mesh indices):
# eye corners (outer, inner, both eyes), nose bridge (between the eyes, lower), nose tip, nose
# base, nostril wings, face sides at the eyes' height, forehead centre.
RIGID_VERTICES = (33, 133, 362, 263, 168, 6, 1, 2, 98, 327, 234, 454, 151)
# Signature distance (RMS difference of the normalized distances) above which a photo is named
# as a different face. Measured on the dev clips' frames as photos (scripts/bench_photo_identity.py,
# docs/packbuild.md "photos.identity"): one person's frames lie up to 0.027-0.032 from their median;
# in folders of 20 photos of one person and 3 of another, 0.03 names 1.2 % of the majority's photos
# and 77 % of the other person's.
DIFFERENT_FACE_DISTANCE = 0.03


def face_signature(xy: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Scale-, translation- and rotation-invariant shape signature of face meshes.

    Parameters
    ----------
    xy
        ``(T, V, 2)`` mesh vertices in px (MediaPipe's 478-vertex mesh, V > max(RIGID_VERTICES));
        NaN where there is no face.
    z
        ``(T, V)`` the vertices' relative depth, px (same scale as ``xy``).

    Returns
    -------
    numpy.ndarray
        ``(T, P)`` with P = K (K - 1) / 2 for the K :data:`RIGID_VERTICES`: the Euclidean 3D
        distances ``|p_i - p_j|`` (i < j) divided by their mean over the pairs; NaN rows where
        there is no face.
    """
    xy = np.asarray(xy, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    if xy.ndim != 3 or xy.shape[2] != 2 or z.shape != xy.shape[:2]:
        raise ValueError(f"expected xy (T, V, 2) and z (T, V), got {xy.shape} and {z.shape}")
    if xy.shape[1] <= max(RIGID_VERTICES):
        raise ValueError(f"expected MediaPipe's face mesh (more than {max(RIGID_VERTICES)} vertices), got {xy.shape[1]}")
    index = list(RIGID_VERTICES)
    points = np.concatenate([xy[:, index], z[:, index, None]], axis=2)  # (T, K, 3)
    i, j = np.triu_indices(len(index), k=1)
    distances = np.linalg.norm(points[:, i] - points[:, j], axis=2)  # (T, P)
    with np.errstate(invalid="ignore", divide="ignore"):
        return distances / distances.mean(axis=1, keepdims=True)


def signature_distance(signatures: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """RMS difference between signatures ``(T, P)`` and one ``reference (P,)``: ``(T,)``,
    dimensionless (a fraction of the mean rigid-point distance); NaN where a row is NaN."""
    signatures = np.asarray(signatures, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    if signatures.ndim != 2 or reference.shape != signatures.shape[1:]:
        raise ValueError(f"expected signatures (T, P) and a reference (P,), got {signatures.shape} and {reference.shape}")
    return np.sqrt(np.mean((signatures - reference) ** 2, axis=1))


def majority_outliers(signatures: np.ndarray, *, threshold: float = DIFFERENT_FACE_DISTANCE) -> tuple[np.ndarray, np.ndarray]:
    """Faces whose signature differs from the majority's.

    The majority's signature is the per-component median over the rows with a face (robust
    while fewer than half the faces are another person's).

    Parameters
    ----------
    signatures
        ``(T, P)`` from :func:`face_signature`; NaN rows (no face) are neither counted nor named.
    threshold
        Distance (:func:`signature_distance`) above which a face is named, > 0.

    Returns
    -------
    distance : numpy.ndarray
        ``(T,)`` each row's distance to the majority's signature (NaN without a face).
    differs : numpy.ndarray
        ``(T,)`` bool, ``distance > threshold``.
    """
    signatures = np.asarray(signatures, dtype=np.float64)
    if signatures.ndim != 2:
        raise ValueError(f"expected signatures (T, P), got {signatures.shape}")
    if not threshold > 0:
        raise ValueError(f"threshold: expected a distance > 0, got {threshold!r}")
    face = np.isfinite(signatures).all(axis=1)
    distance = np.full(len(signatures), np.nan)
    if face.any():
        distance[face] = signature_distance(signatures[face], np.median(signatures[face], axis=0))
    return distance, np.nan_to_num(distance, nan=0.0) > threshold
