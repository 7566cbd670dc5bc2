"""Sec. 9 synthesis: the 3D QP against an independent solver, vertex compositing and blending."""

import numpy as np
import pytest
from scipy.optimize import minimize

from stages.mesh3d.synthesis import composite_vertices, subregion_coefficients_3d, synthesize_3d


def independent_qp(examples: np.ndarray, target: np.ndarray) -> np.ndarray:
    """min ||target - sum c_i E_i||^2 on the simplex, by SLSQP (examples (M, D), target (D,))."""
    M = len(examples)
    res = minimize(
        lambda c: np.sum((target - c @ examples) ** 2),
        np.full(M, 1.0 / M),
        jac=lambda c: -2.0 * examples @ (target - c @ examples),
        bounds=[(0.0, 1.0)] * M,
        constraints=[{"type": "eq", "fun": lambda c: c.sum() - 1.0}],
        method="SLSQP",
        options={"ftol": 1e-14, "maxiter": 500},
    )
    return res.x


def test_qp_on_3n_vectors_matches_an_independent_solve():
    rng = np.random.default_rng(1)
    M, N, T = 5, 7, 4
    examples = rng.normal(0.0, 10.0, (M, N, 3)) + np.array([0.0, 0.0, 300.0])
    targets = rng.normal(0.0, 10.0, (T, N, 3)) + np.array([0.0, 0.0, 300.0])
    members = np.zeros((2, N), bool)
    members[0, :4] = True
    members[1, 3:] = True
    coeffs = subregion_coefficients_3d(examples, targets, members)
    assert coeffs.shape == (T, 2, M)
    for t in range(T):
        for s in range(2):
            idx = np.flatnonzero(members[s])
            ref = independent_qp(examples[:, idx].reshape(M, -1), targets[t, idx].reshape(-1))
            obj = lambda c: np.sum((targets[t, idx].reshape(-1) - c @ examples[:, idx].reshape(M, -1)) ** 2)
            assert obj(coeffs[t, s]) <= obj(ref) + 1e-6 * max(obj(ref), 1.0)
            np.testing.assert_allclose(coeffs[t, s], ref, atol=1e-4)
    assert np.all(coeffs >= 0) and np.allclose(coeffs.sum(-1), 1.0)


def test_an_example_is_reproduced_exactly_and_a_mix_inside_the_hull_too():
    rng = np.random.default_rng(2)
    examples = rng.normal(0.0, 5.0, (4, 6, 3))
    members = np.ones((1, 6), bool)
    mix = 0.3 * examples[0] + 0.7 * examples[2]
    vertices, coeffs = synthesize_3d(examples, np.stack([examples[1], mix]), members)
    np.testing.assert_allclose(vertices[0], examples[1], atol=1e-4)
    np.testing.assert_allclose(vertices[1], mix, atol=1e-4)


def test_boundary_vertices_are_blended_by_position_and_outsiders_kept():
    examples = np.zeros((2, 4, 3))
    examples[1] = 1.0
    members = np.array([[True, True, False, False], [False, True, True, False]])
    coeffs = np.array([[[1.0, 0.0], [0.0, 1.0]]])  # region 0 -> example 0, region 1 -> example 1
    fallback = np.full((1, 4, 3), 7.0)
    out = composite_vertices(examples, coeffs, members, fallback)
    np.testing.assert_allclose(out[0, 0], 0.0)
    np.testing.assert_allclose(out[0, 1], 0.5)  # shared by both: the mean of the two subregion meshes
    np.testing.assert_allclose(out[0, 2], 1.0)
    np.testing.assert_allclose(out[0, 3], 7.0)  # in no subregion: the input position


def test_shapes_are_checked():
    with pytest.raises(ValueError, match="examples"):
        subregion_coefficients_3d(np.zeros((3, 4, 2)), np.zeros((1, 4, 2)), np.ones((1, 4), bool))
    with pytest.raises(ValueError, match="targets"):
        subregion_coefficients_3d(np.zeros((3, 4, 3)), np.zeros((1, 5, 3)), np.ones((1, 4), bool))
