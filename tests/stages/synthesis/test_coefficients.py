"""The synthesis.coefficients stage: synthesize's coefficients laid out by name for write.data."""

import numpy as np
import pytest

from runner.stage import Context, StageError
from stages.synthesis.build import build_synthesis_model
from stages.synthesis.coefficients import NameCoefficients, SubregionQP
from tests.stages.synthesis.synthetic import make_pack


def test_coefficients_stage_layout_and_values():
    pack = make_pack()
    model = build_synthesis_model(pack)
    rng = np.random.default_rng(0)
    xy = pack.standard.points[None] + rng.normal(0, 1.5, (5, 16, 2))
    ref, _ = SubregionQP(model).coefficients(xy)
    ctx = Context("cpu", lambda p: None)
    bundle = NameCoefficients().run({"model": model, "coeffs": {"coeffs": ref.numpy()}}, {}, ctx)["coefficients"]
    assert bundle["subregions"].tolist() == [f"cell{i}{j}" for j in range(2) for i in range(3)] + ["teeth"]
    assert bundle["examples"].tolist() == ["ex0", "ex1", "ex2", "ex3", "teeth0", "teeth1"]
    coeff = bundle["coeff"]
    assert coeff.shape == (5, 7, 6)
    assert np.isnan(coeff[:, :6, 4:]).all() and np.isnan(coeff[:, 6, :4]).all()  # not candidates
    np.testing.assert_allclose(np.nansum(coeff, -1), 1.0, atol=1e-9)
    np.testing.assert_array_equal(coeff[:, :6, :4], ref[:, :6, :4].numpy())
    np.testing.assert_array_equal(coeff[:, 6, 4:], ref[:, 6, :2].numpy())
    with pytest.raises(StageError, match="shape"):
        NameCoefficients().run({"model": model, "coeffs": {"coeffs": ref.numpy()[:, :3]}}, {}, ctx)
