"""Stage wrappers of motion propagation: ``propagate.train`` and ``propagate.hierarchical``."""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from runner.stage import Context, Param, SequenceStage, StageError
from stages.geometry.bundles import DISPLACEMENTS, POINTS
from stages.pack.bundle_types import LAYOUT, PACK_GEOMETRY
from stages.propagation.bundles import PCA_MODEL
from stages.pack.bundles import layout_and_geometry
from stages.propagation.hierarchical_pca import HierarchicalPCA, fit_hierarchical_pca
from stages.propagation.propagate import motion_propagation


class TrainHierarchicalPCA(SequenceStage):
    """Offline: hierarchical PCA of an actor pack's captured geometries (Sec. 10, 14), from
    ``pack.load``'s ``layout`` and ``geometry`` (neither reads the pack's images)."""

    name = "propagate.train"
    version = "2"
    doc = "hierarchical PCA (1 + 4 + 16 feature point sets) of the pack's captured geometries"
    inputs = {"layout": LAYOUT, "geometry": PACK_GEOMETRY}
    outputs = {"pca_model": PCA_MODEL}
    params = (
        Param("n_components", int, 8, "most principal components kept per feature point set (paper: 5-10)", min=1, max=256),
        Param(
            "variance_kept",
            float,
            1.0,
            "also stop at this fraction of explained variance, in [0.01, 1] (1.0: off)",
            min=0.01,
            max=1.0,
        ),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        try:
            layout, geometry = layout_and_geometry(inputs["layout"], inputs["geometry"])
            model = fit_hierarchical_pca(
                geometry.neutral,
                geometry.captured,
                layout.feature_point_sets,
                n_components=int(params["n_components"]),
                variance_kept=float(params["variance_kept"]),
                point_names=layout.point_names,
            )
        except ValueError as exc:
            raise StageError(f"{self.name}: {exc}") from None
        ctx.log.info(
            "hierarchical PCA: %d sets, components kept %s",
            model.n_sets,
            [c.shape[1] for c in model.components],
        )
        return {"pca_model": model.to_bundle()}


#: Keys of the input bundle passed on as they are: its clip's frame rate and size, and the
#: mapping's per-frame flags (``map.expression``: range limited, lips kept apart, states beyond the
#: pack), so that the run's data file records them beside the geometry they describe.
PASSED_ON = ("fps", "size", "range_limited", "lips_clamped", "state_names", "beyond_pack", "coverage", "state_values")


class HierarchicalPropagation(SequenceStage):
    """Runtime: displacements of all feature points from a tracked subset (Sec. 10.1).

    Give exactly one of ``displacements`` (from the neutral, in the neutral's frame) or
    ``points`` (positions in the neutral's frame, i.e. after motion compensation); their
    ``valid`` mask is the input point set of each frame. Outputs the displacements of all points
    and the same as a geometry, ``points.xy = neutral + d`` (the target geometry per frame).
    """

    name = "propagate.hierarchical"
    version = "3"
    doc = "hierarchical-PCA motion propagation of a tracked subset to all feature points"
    inputs = {"pca_model": PCA_MODEL, "displacements": DISPLACEMENTS, "points": POINTS}
    optional_inputs = frozenset({"displacements", "points"})
    outputs = {"displacements": DISPLACEMENTS, "points": POINTS}
    params = (
        Param(
            "stop_progress_px",
            float,
            1e-3,
            "stop when the input points move less than this between iterations, px",
            min=0.0,
            max=1000.0,
        ),
        Param("max_iterations", int, 200, "iteration cap per frame", min=1, max=100_000),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        try:
            model = HierarchicalPCA.from_bundle(inputs["pca_model"], source=f"{self.name}: input 'pca_model'")
        except ValueError as exc:
            raise StageError(str(exc)) from None
        given = [port for port in ("displacements", "points") if inputs.get(port) is not None]
        if len(given) != 1:
            raise StageError("propagate.hierarchical: connect exactly one of the inputs 'displacements' or 'points'")
        port = given[0]
        bundle = inputs[port]
        field = "d" if port == "displacements" else "xy"
        for key in (field, "valid"):
            if key not in bundle:
                raise StageError(f"propagate.hierarchical: input '{port}' has no field '{key}'")
        values = np.asarray(bundle[field], dtype=np.float64)
        if values.ndim != 3 or values.shape[1:] != (model.n_points, 2):
            raise StageError(
                f"propagate.hierarchical: input '{port}' field '{field}' is {values.shape}, "
                f"the pca_model has {model.n_points} points"
            )
        _check_names(model, bundle, port)
        displacements = values if port == "displacements" else values - model.neutral[None]
        try:
            result = motion_propagation(
                model,
                displacements,
                np.asarray(bundle["valid"], dtype=bool),
                stop_progress_px=float(params["stop_progress_px"]),
                max_iterations=int(params["max_iterations"]),
            )
        except ValueError as exc:
            raise StageError(f"{self.name}: input '{port}': {exc}") from None
        ctx.progress(values.shape[0])
        has_input = result.iterations > 0
        out = {
            "d": result.displacements,
            "valid": np.repeat(has_input[:, None], model.n_points, axis=1),
            "names": np.array(model.point_names, dtype=str),
            "iterations": result.iterations,
            "input_error_px": result.input_error_px,
        }
        for key in PASSED_ON:
            if key in bundle:
                out[key] = np.asarray(bundle[key])
        geometry = {key: value for key, value in out.items() if key != "d"}
        geometry["xy"] = model.neutral[None] + result.displacements
        return {"displacements": out, "points": geometry}


def _check_names(model: HierarchicalPCA, bundle: Mapping[str, np.ndarray], port: str) -> None:
    """Raise StageError when the input's point names disagree with the model's."""
    if "names" not in bundle or not any(model.point_names):
        return
    names = tuple(str(n) for n in np.asarray(bundle["names"]))
    if names != model.point_names:
        bad = next((i for i, (a, b) in enumerate(zip(names, model.point_names)) if a != b), min(len(names), model.n_points))
        raise StageError(
            f"propagate.hierarchical: input '{port}' field 'names' differs from the pca_model's layout at point {bad}"
        )
