"""The linear estimator of Valente & Dugelay: ``L = M Lambda^T (Lambda Lambda^T)^-1``.

Each training sample i gives an observation ``lambda_i = (r_x, r_y, r_z, alpha_{1,1}, ...,
alpha_{q,p}, 1)`` (head rotation, eigenfeature scores; the trailing 1 is an intercept, which the
paper's formula lacks: its parameters are not centred) and its animation parameters ``mu_i``.
``M = (mu_1 | ... | mu_m)`` ``(C, m)`` and ``Lambda = (lambda_1 | ... | lambda_m)`` ``(d, m)``;
``L`` ``(C, d)`` minimizes ``||M - L Lambda||^2``, so ``mu = L lambda`` for a new frame.

The model keeps the normal equations ``G = Lambda Lambda^T`` and ``H = M Lambda^T`` rather than
``L`` alone, so that an estimator over a subset of the observation's rows (a feature masked in a
frame) is ``H_S (G_SS)^-1``, exact least squares on the same training set without its rows.
Ridge: ``(G_SS + ridge * m * diag(s_S^2))`` with ``s`` the RMS of each row over the training set
(0 for the intercept), i.e. ridge on standardized observations.
"""

from __future__ import annotations

import numpy as np


def normal_equations(observations: np.ndarray, parameters: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``G = Lambda Lambda^T`` ``(d, d)``, ``H = M Lambda^T`` ``(C, d)`` and the RMS ``s`` ``(d,)``.

    Parameters
    ----------
    observations : (m, d) float
        ``lambda_i^T`` per row (the paper's ``Lambda^T``).
    parameters : (m, C) float
        ``mu_i^T`` per row (``M^T``).
    """
    lam = np.asarray(observations, dtype=np.float64)
    mu = np.asarray(parameters, dtype=np.float64)
    if lam.ndim != 2 or mu.ndim != 2 or lam.shape[0] != mu.shape[0]:
        raise ValueError(f"expected observations (m, d) and parameters (m, C), got {lam.shape} and {mu.shape}")
    return lam.T @ lam, mu.T @ lam, np.sqrt((lam**2).mean(axis=0))


def solve_estimator(
    gram: np.ndarray,
    cross: np.ndarray,
    rms: np.ndarray,
    *,
    count: int,
    ridge: float = 0.0,
    rows: np.ndarray | None = None,
    intercept: int | None = None,
) -> np.ndarray:
    """``L_S = H_S (G_SS + ridge * count * diag(s_S^2))^-1`` ``(C, |S|)`` over the observation rows ``S``.

    Parameters
    ----------
    gram, cross, rms
        From :func:`normal_equations`.
    count : int
        ``m``, the number of training samples (scales the ridge).
    ridge : float
        0 for the paper's least squares.
    rows : (|S|,) int, optional
        Observation rows used (all by default).
    intercept : int, optional
        Row index of the constant 1 (not penalized).
    """
    d = gram.shape[0]
    rows = np.arange(d) if rows is None else np.asarray(rows, dtype=np.int64)
    if ridge < 0:
        raise ValueError(f"expected ridge >= 0, got {ridge}")
    penalty = ridge * count * rms[rows] ** 2
    if intercept is not None:
        penalty[rows == intercept] = 0.0
    A = gram[np.ix_(rows, rows)] + np.diag(penalty)
    return np.linalg.lstsq(A.T, cross[:, rows].T, rcond=None)[0].T


def fit_linear_estimator(
    observations: np.ndarray, parameters: np.ndarray, *, ridge: float = 0.0, intercept: int | None = None
) -> np.ndarray:
    """``L`` ``(C, d)`` from training pairs (rows of ``observations (m, d)``, ``parameters (m, C)``)."""
    gram, cross, rms = normal_equations(observations, parameters)
    return solve_estimator(gram, cross, rms, count=len(observations), ridge=ridge, intercept=intercept)
