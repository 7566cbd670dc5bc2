"""Expression synthesis in 3D (Sec. 9): per-subregion convex combinations of example meshes.

For every face subregion R the new expression's 3D feature points ``G^R`` (a 3n-dimensional
vector) are projected onto the convex hull of the examples' ``G^R_i`` by the QP of eq. 2-5,
solved by the same batched interior-point solver as the 2D case
(:func:`stages.synthesis.qp.project_onto_convex_hull`). Each subregion's mesh is the convex
combination ``sum_i c^R_i E_i`` of its examples' vertex positions; the subregion meshes are then
composited and blended along their shared boundaries by vertex position: a vertex takes the mean
of the positions the subregions that hold it give it (a boundary vertex of two subregions, the
average of both), the 3D counterpart of the image blending of eq. 6-7. Vertices in no face
subregion keep their input position.
"""

from __future__ import annotations

import numpy as np

__all__ = ["subregion_coefficients_3d", "composite_vertices", "synthesize_3d"]


def _check(examples: np.ndarray, members: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    examples = np.asarray(examples, np.float64)
    members = np.asarray(members, bool)
    if examples.ndim != 3 or examples.shape[2] != 3 or len(examples) < 1:
        raise ValueError(f"examples must be (M, N, 3) with M >= 1, got {examples.shape}")
    if members.ndim != 2 or members.shape[1] != examples.shape[1]:
        raise ValueError(f"members must be (S, {examples.shape[1]}) bool, got {members.shape}")
    return examples, members


def subregion_coefficients_3d(
    examples: np.ndarray, targets: np.ndarray, members: np.ndarray, *, device: str = "cpu"
) -> np.ndarray:
    """Convex-combination coefficients of each subregion for each frame (eq. 2-5 on 3n-vectors).

    Parameters
    ----------
    examples : (M, N, 3) float
        Example geometries ``E_i``, mm.
    targets : (T, N, 3) float
        New expressions ``G`` per frame, mm.
    members : (S, N) bool
        The points of each subregion (G^R).
    device : str
        torch device of the solver.

    Returns
    -------
    (T, S, M) float64
        ``c^R_i >= 0``, summing to one over ``i`` (eq. 4).
    """
    import torch

    from stages.synthesis.qp import project_onto_convex_hull

    examples, members = _check(examples, members)
    targets = np.asarray(targets, np.float64)
    if targets.ndim != 3 or targets.shape[1:] != examples.shape[1:]:
        raise ValueError(f"targets must be (T, {examples.shape[1]}, 3), got {targets.shape}")
    T, M = len(targets), len(examples)
    S, n = len(members), max(int(members.sum(1).max()), 1)
    index = np.zeros((S, n), np.int64)  # every subregion padded to n points (zero weight)
    weight = np.zeros((S, n, 3))
    for s, member in enumerate(members):
        idx = np.flatnonzero(member)
        index[s, : len(idx)] = idx
        weight[s, : len(idx)] = 1.0
    w = torch.as_tensor(weight.reshape(S, -1), device=device)
    G_i = torch.as_tensor(examples[:, index].reshape(M, S, -1).transpose(1, 0, 2).copy(), device=device) * w[:, None]
    G = torch.as_tensor(targets[:, index].reshape(T, S, -1), device=device) * w
    c, _ = project_onto_convex_hull(
        G_i[None].expand(T, -1, -1, -1).reshape(T * S, M, -1),
        G.reshape(T * S, -1),
        weights=w[None].expand(T, -1, -1).reshape(T * S, -1),
    )
    out = c.view(T, S, M).cpu().numpy()
    return out


def composite_vertices(examples: np.ndarray, coeffs: np.ndarray, members: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Composite the subregion meshes and blend them along boundaries by vertex position.

    Parameters
    ----------
    examples : (M, N, 3) float, mm
    coeffs : (T, S, M) float, per-subregion coefficients
    members : (S, N) bool
    fallback : (T, N, 3) float, mm, positions of vertices in no subregion

    Returns
    -------
    (T, N, 3) float64, mm: ``x_j = mean over R holding j of sum_i c^R_i E_i[j]``.
    """
    examples, members = _check(examples, members)
    coeffs = np.asarray(coeffs, np.float64)
    if coeffs.ndim != 3 or coeffs.shape[1:] != (len(members), len(examples)):
        raise ValueError(f"coeffs must be (T, {len(members)}, {len(examples)}), got {coeffs.shape}")
    per_region = np.einsum("tsm,mnk->tsnk", coeffs, examples)  # (T, S, N, 3)
    weight = members.astype(np.float64)
    count = weight.sum(0)
    blended = np.einsum("sn,tsnk->tnk", weight, per_region) / np.maximum(count, 1.0)[None, :, None]
    return np.where((count > 0)[None, :, None], blended, np.asarray(fallback, np.float64))


def synthesize_3d(
    examples: np.ndarray, targets: np.ndarray, members: np.ndarray, *, device: str = "cpu"
) -> tuple[np.ndarray, np.ndarray]:
    """Sec. 9: the 3D expression per frame from 3D target geometries.

    Parameters
    ----------
    examples : (M, N, 3) float, mm
    targets : (T, N, 3) float, mm
    members : (S, N) bool

    Returns
    -------
    vertices : (T, N, 3) float64, mm
    coeffs : (T, S, M) float64
    """
    coeffs = subregion_coefficients_3d(examples, targets, members, device=device)
    return composite_vertices(examples, coeffs, members, targets), coeffs
