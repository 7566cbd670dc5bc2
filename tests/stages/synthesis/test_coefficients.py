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


def test_ridge_px_is_tau_squared_per_point_on_each_subregion():
    import torch
    from stages.synthesis.qp import project_onto_convex_hull

    pack = make_pack()
    model = build_synthesis_model(pack)
    rng = np.random.default_rng(1)
    xy = pack.standard.points[None] + rng.normal(0, 1.5, (3, 16, 2))
    tau = 2.5
    ours, _ = SubregionQP(model, ridge_px=tau).coefficients(xy)
    member = np.asarray(model["subregion_points"], bool)
    for s in range(len(member)):
        teeth = bool(model["subregion_teeth"][s])
        ex = np.asarray(model["teeth_points" if teeth else "example_points"])[:, member[s]].reshape(-1, 2 * member[s].sum())
        target = xy[:, member[s]].reshape(3, -1)
        ref, _ = project_onto_convex_hull(
            torch.from_numpy(np.broadcast_to(ex, (3,) + ex.shape).copy()),
            torch.from_numpy(target),
            ridge=torch.full((3,), member[s].sum() * tau**2, dtype=torch.float64),
        )
        np.testing.assert_allclose(ours[:, s, : len(ex)].numpy(), ref.numpy(), atol=1e-7)
    plain, _ = SubregionQP(model).coefficients(xy)
    assert not np.allclose(ours.numpy(), plain.numpy(), atol=1e-3)
    with pytest.raises(ValueError, match="ridge_px"):
        SubregionQP(model, ridge_px=-1.0)
