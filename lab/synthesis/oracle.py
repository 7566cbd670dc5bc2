"""Texture oracle: the best convex combination per subregion given the true image (benchmark only).

The synthesis chooses each subregion's convex-combination coefficients from geometry (eq. 2-5).
To tell how much of the remaining error is the *choice* of coefficients and how much is beyond
any convex combination of the aligned examples (eq. 1, 6), the oracle fits the coefficients to the
true image instead: for every subregion R, with the true image ``T`` and the aligned examples
``I_i`` in the standard geometry,

    minimize  sum_{p in R} || T(p) - sum_i c_i I_i(p) ||^2   s.t.  sum_i c_i = 1,  c_i >= 0,

the same simplex QP as eq. 2 with pixel colours in place of point positions, solved by
:func:`stages.synthesis.qp.solve_simplex_qp`. ``R`` is the subregion's own pixels (the model's
``region``); in ``global`` mode one problem over the union of the face subregions' pixels gives
every face subregion the same coefficients (the global combination's oracle). The teeth subregion
is fitted over the teeth examples in both modes (Sec. 8). The composited oracle image (with the
eq. 7 blending) is an upper bound for the per-subregion method only up to the blending bands.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from stages.synthesis.qp import solve_simplex_qp

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only; imported where used, so that importing this module stays light
    import torch

__all__ = ["texture_problems", "texture_grams", "texture_oracle"]


def texture_problems(model: Mapping[str, np.ndarray], *, mode: str = "full") -> list[list[int]]:
    """The subregions (coefficient rows) fitted together: one problem per face subregion
    (``full``) or one over all face subregions (``global``), then one per teeth subregion."""
    if mode not in ("full", "global"):
        raise ValueError(f"mode must be 'full' or 'global', got {mode!r}")
    teeth = np.asarray(model["subregion_teeth"], bool)
    face_rows = [s for s in range(len(teeth)) if not teeth[s]]
    problems = [[s] for s in face_rows] if mode == "full" else [face_rows]
    return problems + [[s] for s in range(len(teeth)) if teeth[s]]


def texture_grams(
    model: Mapping[str, np.ndarray], truth: torch.Tensor, *, mode: str = "full"
) -> list[tuple[list[int], torch.Tensor]]:
    """Per problem of :func:`texture_problems`, the Hessians of the oracle's texture error.

    For a problem over the pixels ``R`` with candidate images ``E_i`` (the examples, or the teeth
    examples for a teeth subregion), ``Q_ij = sum_{p in R} (E_i(p) - T(p)) . (E_j(p) - T(p))``, so
    that ``c^T Q c`` is the squared error of the combination ``c`` over ``R`` (``sum c_i = 1``).

    Parameters
    ----------
    model : dict of arrays
        A ``synthesis_model`` bundle (keys ``examples``, ``teeth``, ``region``, ``subregion_teeth``,
        ``size``).
    truth : (B, 3, H, W) float tensor
        The true images warped to the standard geometry, sRGB in [0, 1] (the examples' encoding).
    mode : ``"full"`` or ``"global"``

    Returns
    -------
    list of (rows, Q)
        ``rows``: the coefficient rows of the problem; ``Q``: (B, m, m) float64 on the CPU, ``m``
        the problem's number of candidates (``m = 0`` when it has none or no pixels: skip it).
    """
    import torch

    problems = texture_problems(model, mode=mode)
    W, H = (int(v) for v in model["size"])
    if truth.ndim != 4 or tuple(truth.shape[1:]) != (3, H, W):
        raise ValueError(f"truth must be (B, 3, {H}, {W}), got {tuple(truth.shape)}")
    teeth = np.asarray(model["subregion_teeth"], bool)
    region = np.asarray(model["region"]).reshape(-1)
    B = truth.shape[0]
    target = truth.detach().to("cpu", torch.float64).reshape(B, 3, H * W)
    out = []
    for rows in problems:
        pix = torch.from_numpy(np.flatnonzero(np.isin(region, rows)))
        stack = np.asarray(model["teeth"] if teeth[rows[0]] else model["examples"])
        if len(stack) == 0 or len(pix) == 0:
            out.append((rows, torch.zeros(B, 0, 0, dtype=torch.float64)))
            continue
        E = (
            torch.from_numpy(stack.reshape(len(stack), H * W, 3))
            .index_select(1, pix)
            .to(torch.float64)
            .div(255.0)
            .reshape(len(stack), -1)
        )
        T = target.index_select(2, pix).permute(0, 2, 1).reshape(B, -1)  # (B, 3 P), pixel-major as E
        # ||T - sum c_i E_i||^2 = c^T Q c with Q_ij = (E_i - T).(E_j - T) (sum c_i = 1), expanded
        G, b, t = E @ E.T, T @ E.T, (T * T).sum(-1)
        out.append((rows, G[None] - b[:, :, None] - b[:, None, :] + t[:, None, None]))
    return out


def texture_oracle(model: Mapping[str, np.ndarray], truth: torch.Tensor, *, mode: str = "full") -> torch.Tensor:
    """Per-subregion convex-combination coefficients fitted to true images (see the module docstring).

    Parameters
    ----------
    model : dict of arrays
        A ``synthesis_model`` bundle (keys ``examples``, ``teeth``, ``region``,
        ``subregion_teeth``).
    truth : (B, 3, H, W) float tensor
        The true images warped to the standard geometry, sRGB in [0, 1] (the examples' encoding).
    mode : ``"full"`` (one fit per subregion) or ``"global"`` (one fit over the face subregions)

    Returns
    -------
    (B, S, K) float64 tensor, laid out as :meth:`SubregionQP.coefficients`: face subregions over the
    ``M`` examples, the teeth subregion over the ``Mt`` teeth examples, zero-padded to
    ``K = max(M, Mt)``.
    """
    import torch

    grams = texture_grams(model, truth, mode=mode)
    K = max(len(model["examples"]), len(model["teeth"]), 1)
    coeffs = torch.zeros(truth.shape[0], len(model["subregion_teeth"]), K, dtype=torch.float64)
    for rows, Q in grams:
        if Q.shape[-1]:
            coeffs[:, rows, : Q.shape[-1]] = solve_simplex_qp(2.0 * Q)[:, None, :]
    return coeffs
