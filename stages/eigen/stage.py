"""Stage wrappers of the eigenfeature analysis (Valente & Dugelay): ``train.eigenfeatures`` and
``analyze.eigenfeatures``, a second reading of the performer's expression beside point tracking.

``analyze.eigenfeatures`` outputs, for all layout points (docs/architecture.md), a ``points`` bundle
(the geometry in the frame, placed by the frame's 2D similarity) and a ``displacements`` bundle
in the neutral's frame (``d = x(mu) - x_neutral``: the expression without head motion, what the
compensation stages make of tracked points), which ``map.expression`` takes as it takes
``compensate.pose3d``'s (``pipeline_eigen.yaml``). With a real performer's pack the face model
is the pack driven by the synthesis (:mod:`.packface`) and the frame's layout points give the
similarity (``pipeline_eigen_real.yaml``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from runner.stage import Context, FrameStream, Param, SequenceStage, StageError
from stages.eigen.bundles import EIGEN_MODEL, EIGEN_PARAMETERS
from stages.geometry.bundles import DISPLACEMENTS, HEAD_POSES, POINTS, SIMILARITY
from stages.eigen.model import EigenModel, analyze_frames, parameters_to_points, similarities_from_points
from stages.geometry.rotation import ypr_zyx
from stages.eigen.training import face_model, train_on_renders


class TrainEigenfeatures(SequenceStage):
    """Offline: render the performer's face model under sampled parameters and rotations, PCA of
    each feature's patches, the estimator's normal equations and the parameter -> geometry map.
    The face model: the fixture generator's face for a fixture pack (its 12 expression controls),
    else the pack driven by the synthesis (the PCA of its captured geometries)."""

    name = "train.eigenfeatures"
    version = "2"
    doc = "eigenfeatures (PCA of feature patches) and linear estimator from renders of the performer's face model"
    inputs = {"pack": "dir"}
    outputs = {"model": EIGEN_MODEL}
    params = (
        Param(
            "sampling",
            str,
            "rich",
            "paper: each parameter alone x {-3,0,3} deg X/Y; rich: plus random "
            "combinations under wider rotations (generator: +-25 yaw, +-15 pitch, +-10 roll, the live clip's "
            "range; pack: +-15, +-10, +-10)",
            choices=("paper", "rich"),
        ),
        Param("samples", int, 500, "random combinations added by sampling=rich", min=1, max=100_000),
        Param("seed", int, 0, "random seed of sampling=rich", min=0, max=2**32 - 1),
        Param("q", int, 16, "eigenfeatures per feature", min=1, max=256),
        Param("margin", float, 0.25, "room around each feature's points, fraction of its box", min=0.0, max=10.0),
        Param(
            "blur_px",
            float,
            1.0,
            "Gaussian blur of each patch before PCA, patch px (0: off; 1 measured better than 0, docs/eigen.md)",
            min=0.0,
            max=100.0,
        ),
        Param("normalize", bool, False, "each patch to zero mean and unit standard deviation"),
        Param("supersample", int, 2, "antialiasing of the generator's training renders (the fixture clips: 2)", min=1, max=4),
        Param(
            "variance",
            float,
            0.95,
            "pack face model: share of the captured geometries' variance its PCA parameters reach",
            min=0.01,
            max=1.0,
        ),
        Param("max_params", int, 8, "pack face model: most PCA parameters", min=1, max=64),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        try:
            face = face_model(
                Path(inputs["pack"]),
                supersample=int(params["supersample"]),
                variance=float(params["variance"]),
                max_params=int(params["max_params"]),
            )
            controls, angles = face.sampling(params["sampling"], samples=int(params["samples"]), seed=int(params["seed"]))
            model = train_on_renders(
                face,
                controls,
                angles,
                q=int(params["q"]),
                margin=float(params["margin"]),
                blur_px=float(params["blur_px"]),
                normalize=bool(params["normalize"]),
                progress=ctx.progress,
            )
        except ValueError as exc:
            raise StageError(f"{self.name}: {exc}") from exc
        ctx.log.info(
            "eigenfeatures: %d renders of %d parameters, patches %s, q=%d",
            len(controls),
            len(model.param_names),
            [w.shape for w in model.windows],
            model.q,
        )
        return {"model": model.to_bundle()}


class AnalyzeEigenfeatures(SequenceStage):
    """Runtime: per frame the eigenfeature scores of the patches cut through the frame's
    similarity, with the head rotation, give the animation parameters (mu = L lambda), and the
    parameters the geometry of all layout points: in the neutral's frame (``displacements``, no
    head motion) and in the frame through its similarity (``points``; a 2D model, so out-of-plane
    rotation is not in it). Points of a feature whose patch left the image are flagged invalid.
    The similarity is the ``similarity`` input (neutral -> frame, the model's neutral being the
    clip's, as with the fixture packs) or, given the frame's layout ``points``, fitted on the
    model's rigid points from its neutral (a pack built from footage has its own frame)."""

    name = "analyze.eigenfeatures"
    version = "2"
    doc = "animation parameters and all layout points from eigenfeature scores (Valente & Dugelay)"
    inputs = {"frames": "frames", "similarity": SIMILARITY, "points": POINTS, "pose": HEAD_POSES, "model": EIGEN_MODEL}
    optional_inputs = frozenset({"similarity", "points", "pose", "model"})
    outputs = {"points": POINTS, "displacements": DISPLACEMENTS, "parameters": EIGEN_PARAMETERS}
    params = (
        Param("model_file", str, "", "a trained model (.npz of train.eigenfeatures) instead of the model input", file=True),
        Param("rotation", bool, True, "head rotation from the pose input in the estimator's observation (paper)"),
        Param(
            "ridge",
            float,
            0.0,
            "ridge of the estimator on standardized observations (0: the paper's least squares)",
            min=0.0,
            max=1e6,
        ),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        model = self.model(inputs, params)
        similarity, valid, sim = self.similarity(inputs, model)
        frames: FrameStream = inputs["frames"]
        T = len(similarity)
        if frames.info.frames != T:
            raise StageError(f"{self.name}: the similarity has {T} frames, input 'frames' {frames.info.frames}")
        angles = None
        if params["rotation"]:
            pose = inputs.get("pose")
            if pose is None:
                raise StageError(f"{self.name}: rotation=true needs the input 'pose' (or set rotation=false)")
            if len(pose["R"]) != T:
                raise StageError(f"{self.name}: input 'pose' field 'R' has {len(pose['R'])} frames, expected {T}")
            angles = ypr_zyx(pose["R"])
            valid &= np.asarray(pose["valid"], dtype=bool)
        mu, feature_valid = analyze_frames(model, _frames(frames, ctx), similarity, valid, angles, ridge=float(params["ridge"]))
        read = ~np.isnan(mu).any(axis=1)
        expression = parameters_to_points(model, np.where(read[:, None], mu, 0.0))
        xy = parameters_to_points(model, np.where(read[:, None], mu, 0.0), similarity)
        point_valid = np.repeat(read[:, None], len(model.point_names), axis=1)
        for j, window in enumerate(model.windows):
            point_valid[np.ix_(~feature_valid[:, j], list(window.points))] = False
        names = np.array(model.point_names, dtype=str)
        points = {"xy": xy, "valid": point_valid, "names": names}
        displacements = {
            "d": expression - model.neutral[None],
            "valid": point_valid,
            "names": names,
            "neutral": model.neutral.copy(),
        }
        for scalar in ("fps", "size"):
            if scalar in sim:
                points[scalar] = displacements[scalar] = np.asarray(sim[scalar])
        parameters = {
            "params": mu,
            "names": np.array(model.param_names, dtype=str),
            "valid": read,
            "feature_valid": feature_valid,
            "feature_names": np.array([w.name for w in model.windows], dtype=str),
        }
        return {"points": points, "displacements": displacements, "parameters": parameters}

    def similarity(self, inputs: Mapping[str, Any], model: EigenModel) -> tuple[np.ndarray, np.ndarray, Mapping[str, Any]]:
        """Similarities ``(T, 4)`` neutral -> frame, their validity ``(T,)`` and the bundle they came
        from (for ``fps``, ``size``): the input ``similarity`` or fitted on the input ``points``."""
        given = [port for port in ("similarity", "points") if inputs.get(port) is not None]
        if len(given) != 1:
            raise StageError(f"{self.name}: give exactly one of the inputs 'similarity' or 'points', got {given}")
        port = given[0]
        bundle = inputs[port]
        keys = ("params", "valid") if port == "similarity" else ("xy", "valid", "names")
        for key in keys:
            if key not in bundle:
                raise StageError(f"{self.name}: input '{port}' has no field '{key}'")
        if port == "similarity":
            return np.asarray(bundle["params"], dtype=np.float64), np.asarray(bundle["valid"], dtype=bool).copy(), bundle
        names = [str(n) for n in bundle["names"]]
        if names != list(model.point_names):
            raise StageError(
                f"{self.name}: input 'points' field 'names': expected the model's {len(model.point_names)} "
                f"layout points in its order, got {len(names)} names"
            )
        try:
            similarity, valid = similarities_from_points(model, bundle["xy"], bundle["valid"])
        except ValueError as exc:
            raise StageError(f"{self.name}: input 'points': {exc}") from exc
        return similarity, valid, bundle

    def model(self, inputs: Mapping[str, Any], params: Mapping[str, Any]) -> EigenModel:
        """The model from the input port or ``model_file`` (exactly one)."""
        given = inputs.get("model")
        path = str(params["model_file"])
        if (given is None) == (not path):
            raise StageError(f"{self.name}: give exactly one of the input 'model' or the parameter model_file")
        if path:
            try:
                with np.load(path, allow_pickle=False) as data:
                    given = {k: data[k] for k in data.files}
            except (OSError, ValueError) as exc:
                raise StageError(f"{self.name}: model_file {path}: cannot read it as an npz ({exc})") from exc
        try:
            return EigenModel.from_bundle(given)
        except ValueError as exc:
            raise StageError(f"{self.name}: {path or 'input model'}: {exc}") from exc


def _frames(stream: FrameStream, ctx: Context) -> Iterator[np.ndarray]:
    """The stream's frames one by one, reporting progress per chunk."""
    for _, chunk in stream.chunks():
        yield from chunk
        ctx.progress(len(chunk))
