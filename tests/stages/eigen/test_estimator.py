import numpy as np
import pytest

from stages.eigen.estimator import fit_linear_estimator, normal_equations, solve_estimator


def test_least_squares_recovers_a_known_linear_map_exactly():
    rng = np.random.default_rng(3)
    lam = np.column_stack([rng.normal(size=(200, 9)), np.ones(200)])  # intercept last
    L_true = rng.normal(size=(5, 10))
    L = fit_linear_estimator(lam, lam @ L_true.T)
    np.testing.assert_allclose(L, L_true, atol=1e-10)


def test_subset_of_rows_is_least_squares_without_those_rows():
    rng = np.random.default_rng(4)
    lam = np.column_stack([rng.normal(size=(150, 6)), np.ones(150)])
    mu = rng.normal(size=(150, 3))
    rows = np.array([0, 2, 5, 6])
    gram, cross, rms = normal_equations(lam, mu)
    L_sub = solve_estimator(gram, cross, rms, count=150, rows=rows)
    direct = np.linalg.lstsq(lam[:, rows], mu, rcond=None)[0].T
    np.testing.assert_allclose(L_sub, direct, atol=1e-10)


def test_ridge_shrinks_but_leaves_the_intercept_free():
    rng = np.random.default_rng(5)
    lam = np.column_stack([rng.normal(size=(100, 4)), np.ones(100)])
    mu = lam @ np.array([[1.0, -2.0, 0.5, 0.0, 3.0]]).T
    plain = fit_linear_estimator(lam, mu)
    ridged = fit_linear_estimator(lam, mu, ridge=10.0, intercept=4)
    assert np.abs(ridged[0, :4]).sum() < 0.5 * np.abs(plain[0, :4]).sum()
    assert abs(ridged[0, 4] - 3.0) < 0.5  # intercept not pulled to 0


def test_shape_mismatch_is_a_value_error():
    with pytest.raises(ValueError, match="observations"):
        fit_linear_estimator(np.ones((5, 3)), np.ones((4, 2)))
    with pytest.raises(ValueError, match="ridge"):
        fit_linear_estimator(np.ones((5, 3)), np.ones((5, 2)), ridge=-1.0)
