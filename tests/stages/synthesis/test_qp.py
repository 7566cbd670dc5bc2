"""The batched interior-point QP (eq. 2-5) against quadprog on random and degenerate problems."""

import numpy as np
import pytest
import torch
from qpsolvers import solve_qp

from stages.synthesis.qp import project_onto_convex_hull, solve_simplex_qp


def quadprog_hull(examples: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, float]:
    """Reference: eq. 5 as 1/2 c^T P c + q^T c with P = 2 G^T G, q = -2 G^T g (tiny ridge for PD)."""
    G = examples.T  # (D, M)
    P = 2.0 * G.T @ G
    P = P + 1e-9 * np.trace(P) / len(P) * np.eye(len(P))
    q = -2.0 * G.T @ target
    m = G.shape[1]
    c = solve_qp(P, q, G=-np.eye(m), h=np.zeros(m), A=np.ones((1, m)), b=np.ones(1), solver="quadprog")
    c = np.clip(c, 0, None) / np.clip(c, 0, None).sum()
    r = target - G @ c
    return c, float(r @ r)


def check(examples: np.ndarray, targets: np.ndarray) -> torch.Tensor:
    coeffs, dist2 = project_onto_convex_hull(torch.from_numpy(examples), torch.from_numpy(targets))
    assert coeffs.dtype == torch.float64
    assert (coeffs >= -1e-9).all()
    np.testing.assert_allclose(coeffs.sum(-1).numpy(), 1.0, atol=1e-9)
    for b in range(len(examples)):
        _, ref = quadprog_hull(examples[b], targets[b])
        ours = float(((targets[b] - coeffs[b].numpy() @ examples[b]) ** 2).sum())
        assert ours == pytest.approx(float(dist2[b]), rel=1e-9, abs=1e-9)
        assert abs(ours - ref) < 1e-6, (b, ours, ref)  # quadprog's optimum to 1e-6
    return coeffs


def face_like(rng: np.random.Generator, B: int, M: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Examples = a base shape plus per-example deformations of a few px; targets near them."""
    base = rng.uniform(100, 500, size=(1, 1, 2 * n))
    examples = base + rng.normal(0, 8, size=(B, M, 2 * n))
    w = rng.dirichlet(np.ones(M), size=B)
    targets = np.einsum("bm,bmd->bd", w, examples) + rng.normal(0, 3, size=(B, 2 * n))
    return examples, targets


def test_random_batch_matches_quadprog():
    rng = np.random.default_rng(0)
    examples, targets = face_like(rng, 40, 15, 12)
    check(examples, targets)


def test_more_examples_than_coordinates():
    rng = np.random.default_rng(1)
    examples, targets = face_like(rng, 20, 15, 3)  # D = 6 < M = 15: Q only semidefinite
    check(examples, targets)


def test_target_far_outside_hull_lands_on_a_vertex():
    rng = np.random.default_rng(2)
    examples = rng.normal(0, 1, size=(1, 5, 4))
    direction = examples[0, 3] - examples[0].mean(0)
    target = examples[0, 3] + 50 * direction  # far beyond vertex 3 along its outward direction
    coeffs = check(examples, target[None])
    assert coeffs[0, 3] > 1 - 1e-6


def test_duplicate_examples():
    rng = np.random.default_rng(3)
    examples, targets = face_like(rng, 10, 6, 8)
    examples[:, 4] = examples[:, 1]
    examples[:, 5] = examples[:, 1]
    check(examples, targets)


def test_point_already_on_hull():
    rng = np.random.default_rng(4)
    examples, _ = face_like(rng, 6, 10, 10)
    targets = examples[:, 7].copy()  # an example itself: distance 0, c = e_7
    targets[3] = 0.5 * examples[3, 2] + 0.5 * examples[3, 5]  # the midpoint of an edge
    coeffs, dist2 = project_onto_convex_hull(torch.from_numpy(examples), torch.from_numpy(targets))
    assert float(dist2.max()) < 1e-6
    np.testing.assert_allclose(coeffs[[0, 1, 2, 4, 5], 7].numpy(), 1.0, atol=1e-6)
    np.testing.assert_allclose(coeffs[3, [2, 5]].numpy(), 0.5, atol=1e-5)


def test_single_example_and_all_equal():
    rng = np.random.default_rng(5)
    ex = rng.normal(size=(3, 1, 6))
    coeffs, dist2 = project_onto_convex_hull(torch.from_numpy(ex), torch.from_numpy(ex[:, 0] + 1))
    np.testing.assert_array_equal(coeffs.numpy(), 1.0)
    np.testing.assert_allclose(dist2.numpy(), 6.0)
    same = np.repeat(ex[:, :1], 4, axis=1)  # four identical examples equal to the target
    coeffs, dist2 = project_onto_convex_hull(torch.from_numpy(same), torch.from_numpy(ex[:, 0]))
    assert torch.isfinite(coeffs).all() and float(dist2.max()) < 1e-12
    np.testing.assert_allclose(coeffs.sum(-1).numpy(), 1.0, atol=1e-12)


def test_general_qp_with_linear_term():
    rng = np.random.default_rng(6)
    B, M = 25, 9
    R = rng.normal(size=(B, M, M))
    Q = R @ R.transpose(0, 2, 1)
    p = rng.normal(size=(B, M)) * 3
    c = solve_simplex_qp(torch.from_numpy(Q), torch.from_numpy(p)).numpy()
    for b in range(B):
        ref = solve_qp(Q[b], p[b], G=-np.eye(M), h=np.zeros(M), A=np.ones((1, M)), b=np.ones(1), solver="quadprog")
        f = lambda x: 0.5 * x @ Q[b] @ x + p[b] @ x
        assert abs(f(c[b]) - f(ref)) < 1e-6


def test_padding_weights_equal_separate_problems():
    rng = np.random.default_rng(7)
    ex_a, t_a = face_like(rng, 1, 8, 5)
    ex_b, t_b = face_like(rng, 1, 8, 3)
    pad = np.zeros((1, 8, 4))
    examples = np.concatenate([ex_a, np.concatenate([ex_b, pad], -1)])
    targets = np.concatenate([t_a, np.concatenate([t_b, np.full((1, 4), 123.0)], -1)])
    weights = np.ones_like(targets)
    weights[1, 6:] = 0
    c, _ = project_onto_convex_hull(torch.from_numpy(examples), torch.from_numpy(targets), weights=torch.from_numpy(weights))
    c_b, _ = project_onto_convex_hull(torch.from_numpy(ex_b), torch.from_numpy(t_b))
    ours = ((t_b[0] - c[1].numpy() @ ex_b[0]) ** 2).sum()
    ref = ((t_b[0] - c_b[0].numpy() @ ex_b[0]) ** 2).sum()
    assert abs(ours - ref) < 1e-6


def test_ridge_matches_quadprog_with_the_tikhonov_term():
    rng = np.random.default_rng(8)
    examples, targets = face_like(rng, 12, 10, 6)
    lam = rng.uniform(0, 2000, size=12)
    c, dist2 = project_onto_convex_hull(torch.from_numpy(examples), torch.from_numpy(targets), ridge=torch.from_numpy(lam))
    for b in range(len(examples)):
        G = examples[b].T
        P = 2.0 * (G.T @ G + lam[b] * np.eye(G.shape[1]))
        ref = solve_qp(
            P,
            -2.0 * G.T @ targets[b],
            G=-np.eye(G.shape[1]),
            h=np.zeros(G.shape[1]),
            A=np.ones((1, G.shape[1])),
            b=np.ones(1),
            solver="quadprog",
        )
        f = lambda x: ((targets[b] - x @ examples[b]) ** 2).sum() + lam[b] * x @ x
        assert abs(f(c[b].numpy()) - f(ref)) < 1e-6 * max(1.0, f(ref))
        assert float(dist2[b]) == pytest.approx(((targets[b] - c[b].numpy() @ examples[b]) ** 2).sum(), rel=1e-9)


def test_ridge_spreads_the_combination_and_zero_is_eq2():
    rng = np.random.default_rng(9)
    examples, targets = face_like(rng, 6, 7, 5)
    ex, tg = torch.from_numpy(examples), torch.from_numpy(targets)
    plain, _ = project_onto_convex_hull(ex, tg)
    zero, _ = project_onto_convex_hull(ex, tg, ridge=torch.zeros(6, dtype=torch.float64))
    np.testing.assert_allclose(zero.numpy(), plain.numpy(), atol=1e-9)
    norms = [
        (project_onto_convex_hull(ex, tg, ridge=torch.full((6,), lam, dtype=torch.float64))[0] ** 2).sum(-1)
        for lam in (0.0, 1e2, 1e4, 1e9)
    ]
    assert all(bool((a >= b - 1e-9).all()) for a, b in zip(norms, norms[1:]))  # ||c||^2 falls as lambda grows
    np.testing.assert_allclose(norms[-1].numpy(), 1 / 7, atol=1e-5)  # towards the uniform combination
    with pytest.raises(ValueError, match="ridge"):
        project_onto_convex_hull(ex, tg, ridge=torch.full((6,), -1.0, dtype=torch.float64))
