"""Coefficients learned from the footage a pack was built from (used by the benchmarks, not by a stage).

Eq. 2-5 choose a subregion's convex-combination coefficients from its few feature points alone,
and on real faces those points predict only moderately which examples' texture fits
(docs/synthesis.md, "Per-subregion vs global on real faces"). The footage the pack was built from
has both, geometry and texture, for many more frames than the examples: for each such *footage
frame* the texture oracle (:mod:`lab.synthesis.oracle`) gives every subregion's best convex
combination of the aligned examples. For a new geometry, each face subregion R takes

    c^R = (1 / k) sum_{f in N_k^R} c^R_f,

the mean of the oracle coefficients ``c^R_f`` of the ``k`` footage frames ``N_k^R`` whose points of
that subregion (G^R of eq. 2) are nearest to the new geometry's (RMS point distance): a k-nearest-
neighbour regression from the subregion's geometry to its texture combination, on the simplex
like eq. 4. In ``global`` mode (the fair baseline) one neighbourhood over all face points and the
global oracle's coefficients serve every face subregion. The teeth subregion keeps eq. 2 over the
teeth examples (Sec. 8) in both modes.

``k`` is chosen per mode from the footage itself by blocked cross-validation: the footage frames
are cut into ``folds`` contiguous runs in time (neighbouring frames are near copies, so leaving out
single frames would always pick ``k = 1``); each run's frames are predicted from the other runs'
and the texture error ``c^T Q_f c`` (:func:`lab.synthesis.oracle.texture_grams`), summed over
subregions and frames, picks ``k``.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from stages.synthesis.coefficients import SubregionQP
from lab.synthesis.oracle import texture_grams
from stages.synthesis.qp import solve_simplex_qp

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only; imported where used, so that importing this module stays light
    import torch

__all__ = ["K_CANDIDATES", "subregion_distance", "nearest_mean", "cv_errors", "FootageCoefficients"]

K_CANDIDATES = (1, 2, 3, 5, 8, 12, 16, 24)


def subregion_distance(points: np.ndarray, footage: np.ndarray, member: np.ndarray) -> np.ndarray:
    """RMS distance over a subregion's points between every geometry and every footage geometry.

    Parameters
    ----------
    points : (B, N, 2) float, px
    footage : (T, N, 2) float, px
    member : (N,) bool
        The subregion's points (G^R).

    Returns
    -------
    (B, T) float64, px.
    """
    a = np.asarray(points, np.float64)[:, member]
    b = np.asarray(footage, np.float64)[:, member]
    return np.sqrt(((a[:, None] - b[None]) ** 2).sum(-1).mean(-1))


def nearest_mean(distance: np.ndarray, values: torch.Tensor, k: int) -> torch.Tensor:
    """Per row of ``distance``, the mean of ``values`` over its ``k`` nearest columns.

    Parameters
    ----------
    distance : (B, T) float
    values : (T, M) tensor
    k : int, 1 <= k <= T (ties broken by the lower column index)

    Returns
    -------
    (B, M) tensor.
    """
    import torch

    if not 1 <= k <= distance.shape[1]:
        raise ValueError(f"k must be in 1..{distance.shape[1]}, got {k}")
    nearest = np.argsort(distance, axis=1, kind="stable")[:, :k]
    return values[torch.from_numpy(nearest)].mean(1)


def cv_errors(distance: np.ndarray, coeffs: torch.Tensor, gram: torch.Tensor, *, ks: Sequence[int], folds: int) -> np.ndarray:
    """Blocked cross-validation error of :func:`nearest_mean` for each ``k``.

    Parameters
    ----------
    distance : (T, T) float
        Footage frame to footage frame (in time order).
    coeffs : (T, M) tensor
        The oracle's coefficients per footage frame.
    gram : (T, M, M) tensor
        Per footage frame ``Q_f``: ``c^T Q_f c`` is its texture error under ``c``.
    ks : sequence of int
    folds : int
        Contiguous runs of frames, each predicted from the others (``2 <= folds <= T``).

    Returns
    -------
    (len(ks),) float64: the summed texture error of the predictions (``k`` capped at the
    training frames' number).
    """
    import torch

    T = len(distance)
    if not 2 <= folds <= T:
        raise ValueError(f"folds must be in 2..{T} (the footage frames), got {folds}")
    fold = np.minimum(np.arange(T) * folds // T, folds - 1)
    errors = np.zeros(len(ks))
    for f in range(folds):
        train, test = np.flatnonzero(fold != f), np.flatnonzero(fold == f)
        Q = gram[torch.from_numpy(test)]
        for j, k in enumerate(ks):
            c = nearest_mean(distance[np.ix_(test, train)], coeffs[torch.from_numpy(train)], min(k, len(train)))
            errors[j] += float(torch.einsum("bi,bij,bj->", c, Q, c))
    return errors


class FootageCoefficients:
    """Per-subregion coefficients by k-nearest-neighbour regression on footage frames (module docstring).

    Parameters
    ----------
    model : dict of arrays
        A ``synthesis_model`` bundle.
    footage_points : (T, N, 2) float, px
        The footage frames' feature points in the pack's frame (as the synthesis' target
        geometry), in time order.
    footage_standard : (T, 3, H, W) float tensor
        The same frames warped to the standard geometry, sRGB in [0, 1].
    ks : sequence of int
        Candidate neighbourhood sizes for the cross-validation.
    folds : int
        Contiguous runs of the cross-validation.
    batch : int
        Footage frames per call of :func:`texture_grams` (memory).

    Attributes
    ----------
    k : dict
        The chosen ``k`` per mode (``"full"``, ``"global"``).
    cv : dict
        Per mode the cross-validation errors, (len(ks),), aligned with ``ks``.
    """

    def __init__(
        self,
        model: Mapping[str, np.ndarray],
        footage_points: np.ndarray,
        footage_standard: torch.Tensor,
        *,
        ks: Sequence[int] = K_CANDIDATES,
        folds: int = 5,
        batch: int = 16,
    ) -> None:
        import torch

        self.footage_points = np.asarray(footage_points, np.float64)
        N = len(model["standard_points"])
        T = len(self.footage_points)
        if self.footage_points.shape != (T, N, 2) or footage_standard.shape[0] != T:
            raise ValueError(
                f"footage_points must be (T, {N}, 2) and footage_standard (T, 3, H, W) with the same T; "
                f"got {self.footage_points.shape} and {tuple(footage_standard.shape)}"
            )
        if not ks or min(ks) < 1:
            raise ValueError(f"ks must be positive neighbourhood sizes, got {list(ks)}")
        self.qp = SubregionQP(model)
        self.ks = tuple(int(k) for k in ks)
        member = np.asarray(model["subregion_points"], bool)
        teeth = np.asarray(model["subregion_teeth"], bool)
        self.k, self.cv, self.problems = {}, {}, {}
        for mode in ("full", "global"):
            parts = [texture_grams(model, footage_standard[s : s + batch], mode=mode) for s in range(0, T, batch)]
            problems = []
            errors = np.zeros(len(self.ks))
            for p, (rows, _) in enumerate(parts[0]):
                if teeth[rows[0]] or parts[0][p][1].shape[-1] == 0:
                    continue
                gram = torch.cat([part[p][1] for part in parts])
                coeffs = solve_simplex_qp(2.0 * gram)
                points = member[rows].any(0)
                errors += cv_errors(
                    subregion_distance(self.footage_points, self.footage_points, points), coeffs, gram, ks=self.ks, folds=folds
                )
                problems.append((rows, points, coeffs))
            self.problems[mode], self.cv[mode] = problems, errors
            self.k[mode] = min(self.ks[int(np.argmin(errors))], T)

    def coefficients(self, points: np.ndarray, *, mode: str = "full") -> torch.Tensor:
        """Coefficients for target geometries.

        Parameters
        ----------
        points : (B, N, 2) float, px, in the pack's frame
        mode : ``"full"`` or ``"global"``

        Returns
        -------
        (B, S, K) float64 tensor, laid out as :meth:`SubregionQP.coefficients`.
        """
        if mode not in self.k:
            raise ValueError(f"mode must be 'full' or 'global', got {mode!r}")
        coeffs, _ = self.qp.coefficients(points, mode=mode)
        for rows, member, footage_coeffs in self.problems[mode]:
            c = nearest_mean(subregion_distance(points, self.footage_points, member), footage_coeffs, self.k[mode])
            coeffs[:, rows, : c.shape[1]] = c[:, None, :].to(coeffs)
        return coeffs
