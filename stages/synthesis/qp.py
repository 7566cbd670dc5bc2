"""Convex-hull projection of a subregion's geometry (Sec. 6, eq. 2-5), batched in torch.

For a subregion R, the new expression's feature points ``G^R`` are projected onto the convex hull
of the example expressions' points ``G^R_0 ... G^R_m``:

    minimize    || G^R - sum_i c_i G^R_i ||^2                       (eq. 2, expanded as eq. 5)
    subject to  sum_i c_i = 1,  c_i >= 0.

Because the coefficients sum to one, ``G^R - sum_i c_i G^R_i = sum_i c_i (G^R_i - G^R)``, so the
objective equals ``c^T A c`` with ``A = X^T X`` and ``X = (G^R_0 - G^R, ..., G^R_m - G^R)``: the
same minimiser as eq. 5, but with the large constant ``G^RT G^R`` and the cross term cancelled
exactly, which keeps float64 well conditioned for pixel coordinates.

The QP is solved, as in the paper, by a primal-dual interior-point method: Mehrotra's
predictor-corrector on the KKT system of a simplex-constrained QP, for a whole batch of problems
(frames x subregions) at once.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only; imported where used, so that importing this module stays light
    import torch


__all__ = ["solve_simplex_qp", "project_onto_convex_hull"]


def solve_simplex_qp(
    Q: torch.Tensor,
    p: torch.Tensor | None = None,
    *,
    tol: float = 1e-13,
    max_iter: int = 60,
    regularization: float = 1e-10,
) -> torch.Tensor:
    """Minimize ``1/2 c^T Q c + p^T c`` subject to ``sum(c) = 1, c >= 0`` for a batch of problems.

    Primal-dual interior-point method with Mehrotra's predictor-corrector. With dual ``y`` for the
    equality and ``z >= 0`` for the bounds, the perturbed KKT conditions are::

        Q c + p - y 1 - z = 0,    1^T c = 1,    c_i z_i = sigma mu.

    Each Newton step eliminates ``dz`` and solves the reduced system
    ``(Q + diag(z / c) + delta I) dc - 1 dy = h`` with ``1^T dc = -r_p`` by one Cholesky
    factorisation (Schur complement on the single equality). ``delta`` (relative to the problem
    scale) is a static regularisation of the Newton system only, not of the objective: it keeps
    the system positive definite when ``Q`` is only semidefinite (duplicate examples, fewer
    points than examples) while residuals are always evaluated with the true ``Q``.

    Parameters
    ----------
    Q : (B, M, M) tensor
        Symmetric positive semidefinite Hessians.
    p : (B, M) tensor, optional
        Linear terms; zero when omitted.
    tol : float
        A problem stops when ``mu < tol``, ``|1^T c - 1| < tol`` and the dual residual is below
        ``sqrt(tol)``, all in units of the problem scale (the mean of ``diag(Q)``); the batch
        stops when every problem has.
    max_iter : int
        Iteration cap.
    regularization : float
        ``delta`` above, relative to the problem scale.

    Returns
    -------
    (B, M) tensor
        Coefficients on the simplex (clipped at 0 and renormalised to sum exactly to one), on the
        dtype and device of ``Q``.
    """
    import torch

    if Q.ndim != 3 or Q.shape[-1] != Q.shape[-2]:
        raise ValueError(f"Q must be (B, M, M), got {tuple(Q.shape)}")
    B, M, _ = Q.shape
    dtype, device = Q.dtype, Q.device
    if p is None:
        p = torch.zeros(B, M, dtype=dtype, device=device)
    if M == 1:
        return torch.ones(B, 1, dtype=dtype, device=device)
    scale = torch.diagonal(Q, dim1=-2, dim2=-1).abs().mean(-1).clamp_min(torch.finfo(dtype).tiny)
    scale = torch.maximum(scale, p.abs().amax(-1))
    scale = torch.where(scale > 1e-300, scale, torch.ones_like(scale))
    Qs = Q / scale[:, None, None]
    ps = p / scale[:, None]
    eye = torch.eye(M, dtype=dtype, device=device)
    ones = torch.ones(B, M, dtype=dtype, device=device)

    c = torch.full((B, M), 1.0 / M, dtype=dtype, device=device)
    z = torch.ones(B, M, dtype=dtype, device=device)
    y = torch.zeros(B, dtype=dtype, device=device)
    for _ in range(max_iter):
        r_d = torch.einsum("bij,bj->bi", Qs, c) + ps - y[:, None] - z
        r_p = c.sum(-1) - 1.0
        mu = (c * z).sum(-1) / M
        done = (mu < tol) & (r_d.abs().amax(-1) < tol**0.5) & (r_p.abs() < tol)
        if bool(done.all()):
            break
        K = Qs + torch.diag_embed(z / c) + regularization * eye
        L, info = torch.linalg.cholesky_ex(K)
        if bool((info != 0).any()):
            L = torch.linalg.cholesky(K + 1e-8 * eye)

        def newton(r_c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            h = -r_d - r_c / c
            sol = torch.cholesky_solve(torch.stack([h, ones], -1), L)
            Kh, K1 = sol[..., 0], sol[..., 1]
            dy = (-r_p - Kh.sum(-1)) / K1.sum(-1)
            dc = Kh + K1 * dy[:, None]
            dz = (-r_c - z * dc) / c
            return dc, dy, dz

        def step_length(dc: torch.Tensor, dz: torch.Tensor) -> torch.Tensor:
            ratio = torch.cat([torch.where(dc < 0, -c / dc, torch.inf), torch.where(dz < 0, -z / dz, torch.inf)], -1)
            return ratio.amin(-1).clamp(max=1.0)

        dc_a, _, dz_a = newton(c * z)
        a_aff = step_length(dc_a, dz_a)
        mu_aff = ((c + a_aff[:, None] * dc_a) * (z + a_aff[:, None] * dz_a)).sum(-1) / M
        sigma = (mu_aff / mu).clamp(0.0, 1.0) ** 3
        dc, dy, dz = newton(c * z + dc_a * dz_a - (sigma * mu)[:, None])
        alpha = (0.99 * step_length(dc, dz)).clamp(max=1.0)
        alpha = torch.where(done, torch.zeros_like(alpha), alpha)
        c = c + alpha[:, None] * dc
        z = z + alpha[:, None] * dz
        y = y + alpha * dy
    c = c.clamp_min(0.0)
    return c / c.sum(-1, keepdim=True)


def project_onto_convex_hull(
    examples: torch.Tensor,
    target: torch.Tensor,
    *,
    weights: torch.Tensor | None = None,
    ridge: torch.Tensor | None = None,
    tol: float = 1e-13,
    max_iter: int = 60,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Closest point of the convex hull of example geometries to a target geometry (eq. 2-5).

    With ``ridge`` the objective gains a Tikhonov term on the coefficients,
    ``||G^R - sum_i c_i G^R_i||^2 + lambda ||c||^2``: among combinations that fit the points about
    equally well it prefers the one spread over more examples (``||c||^2`` is 1 on a single
    example, ``1/k`` spread evenly over ``k``), which keeps landmark noise from switching the
    texture between examples. ``lambda = 0`` is eq. 2.

    Parameters
    ----------
    examples : (B, M, D) tensor
        ``G^R_i``: for each of ``B`` problems, the ``M`` example expressions' coordinates of the
        subregion's feature points, flattened (``D = 2 n`` for ``n`` points), px.
    target : (B, D) tensor
        ``G^R``: the new expression's coordinates of the same points, px.
    weights : (B, D) tensor, optional
        Per-coordinate 0/1 (or non-negative) weights; lets problems of different sizes share one
        padded batch (a zero weight removes a coordinate from the objective).
    ridge : (B,) tensor, optional
        ``lambda`` per problem, px^2 (>= 0).

    Returns
    -------
    coeffs : (B, M) tensor
        Convex combination coefficients ``c_i`` (eq. 4): ``>= 0``, summing to one.
    distance2 : (B,) tensor
        The geometry term (eq. 5) at ``coeffs``: squared distance of the combination to the
        target, px^2 (the hull distance when ``ridge`` is absent or zero).
    """
    import torch

    if examples.ndim != 3 or target.shape != (examples.shape[0], examples.shape[2]):
        raise ValueError(f"examples must be (B, M, D) and target (B, D); got {tuple(examples.shape)}, {tuple(target.shape)}")
    X = examples - target[:, None, :]
    if weights is not None:
        X = X * weights.sqrt()[:, None, :]
    A = X @ X.transpose(1, 2)
    if ridge is not None:
        if ridge.shape != (examples.shape[0],) or bool((ridge < 0).any()):
            raise ValueError(f"ridge must be (B,) = ({examples.shape[0]},) and >= 0, got shape {tuple(ridge.shape)}")
        A = A + ridge.to(A)[:, None, None] * torch.eye(A.shape[-1], dtype=A.dtype, device=A.device)
    coeffs = solve_simplex_qp(2.0 * A, tol=tol, max_iter=max_iter)
    residual = torch.einsum("bm,bmd->bd", coeffs, X)
    return coeffs, (residual * residual).sum(-1)
