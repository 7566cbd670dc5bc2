"""The synthesis.coefficients stage: the QP over a clip, laid out by name for write.data."""

import numpy as np
import pytest

from runner.stage import Context, StageError
from stages.synthesis.build import build_synthesis_model
from stages.synthesis.coefficients import SolveCoefficients, SubregionQP
from tests.stages.synthesis.synthetic import make_pack


def test_coefficients_stage_layout_and_values():
    pack = make_pack()
    model = build_synthesis_model(pack)
    rng = np.random.default_rng(0)
    xy = pack.standard.points[None] + rng.normal(0, 1.5, (5, 16, 2))
    out = SolveCoefficients().run({"model": model, "points": {"xy": xy}}, {"mode": "full"}, Context("cpu", lambda p: None))
    bundle = out["coefficients"]
    assert bundle["subregions"].tolist() == [f"cell{i}{j}" for j in range(2) for i in range(3)] + ["teeth"]
    assert bundle["examples"].tolist() == ["ex0", "ex1", "ex2", "ex3", "teeth0", "teeth1"]
    coeff = bundle["coeff"]
    assert coeff.shape == (5, 7, 6)
    assert np.isnan(coeff[:, :6, 4:]).all() and np.isnan(coeff[:, 6, :4]).all()  # not candidates
    np.testing.assert_allclose(np.nansum(coeff, -1), 1.0, atol=1e-9)
    ref, _ = SubregionQP(model).coefficients(xy)
    np.testing.assert_allclose(coeff[:, :6, :4], ref[:, :6, :4].numpy())
    np.testing.assert_allclose(coeff[:, 6, 4:], ref[:, 6, :2].numpy())
    with pytest.raises(StageError, match="non-finite"):
        SolveCoefficients().run({"model": model, "points": {"xy": xy * np.nan}}, {"mode": "full"}, Context("cpu", lambda p: None))
