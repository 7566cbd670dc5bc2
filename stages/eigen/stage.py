"""Stage wrappers of the eigenfeature analysis (Valente & Dugelay): ``train.eigenfeatures`` and
``analyze.eigenfeatures``, a second reading of the performer's expression beside point tracking.

``analyze.eigenfeatures`` outputs, for all layout points (docs/CONTRACTS.md), a ``points`` bundle
(the geometry in the frame, placed by the frame's 2D similarity) and a ``displacements`` bundle
in the neutral's frame (``d = x(mu) - x_neutral``: the expression without head motion, what the
compensation stages make of tracked points), which ``map.expression`` takes as it takes
``compensate.pose3d``'s (``pipeline_eigen.yaml``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from runner.stage import Context, FrameStream, Param, SequenceStage, StageError
from stages.eigen.model import EigenModel, analyze_frames, parameters_to_points
from stages.eigen.sampling import paper_sampling, rich_sampling, rotation_angles
from stages.eigen.synthetic import performer_rig, train_on_renders


def training_sampling(kind: str, n_params: int, *, samples: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Controls ``(m, C)`` and angles ``(m, 3)`` of ``kind``: ``paper`` (each parameter alone x 9
    orientations) or ``rich`` (the paper's set plus ``samples`` random combinations under a wider
    range of rotations)."""
    controls, angles = paper_sampling(n_params)
    if kind == "rich":
        more_c, more_a = rich_sampling(n_params, samples, seed=seed)
        controls, angles = np.concatenate([controls, more_c]), np.concatenate([angles, more_a])
    return controls, angles


class TrainEigenfeatures(SequenceStage):
    """Offline: render the performer's face model under sampled parameters and rotations, PCA of
    each feature's patches, the estimator's normal equations and the parameter -> geometry map."""

    name = "train.eigenfeatures"
    version = "1"
    doc = "eigenfeatures (PCA of feature patches) and linear estimator from renders of the performer's face model"
    inputs = {"pack": "dir"}
    outputs = {"model": "eigen_model"}
    params = (
        Param("sampling", str, "rich", "paper: each parameter alone x {-3,0,3} deg X/Y; rich: plus random "
              "combinations under +-25 yaw, +-15 pitch, +-10 roll (the live clip's range)", choices=("paper", "rich")),
        Param("samples", int, 500, "random combinations added by sampling=rich", min=1),
        Param("seed", int, 0, "random seed of sampling=rich"),
        Param("q", int, 16, "eigenfeatures per feature", min=1),
        Param("margin", float, 0.25, "room around each feature's points, fraction of its box", min=0.0),
        Param("blur_px", float, 1.0, "Gaussian blur of each patch before PCA, patch px (0: off; 1 measured better "
              "than 0, docs/eigen.md)", min=0.0),
        Param("normalize", bool, False, "each patch to zero mean and unit standard deviation"),
        Param("supersample", int, 2, "antialiasing of the training renders (the fixture clips: 2)", min=1, max=4),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        try:
            rig = performer_rig(Path(inputs["pack"]))
            controls, angles = training_sampling(params["sampling"], len(rig.param_names),
                                                 samples=int(params["samples"]), seed=int(params["seed"]))
            model = train_on_renders(rig, controls, angles, q=int(params["q"]), margin=float(params["margin"]),
                                     blur_px=float(params["blur_px"]), normalize=bool(params["normalize"]),
                                     supersample=int(params["supersample"]), progress=ctx.progress)
        except ValueError as exc:
            raise StageError(f"{self.name}: {exc}") from exc
        ctx.log.info("eigenfeatures: %d renders, patches %s, q=%d", len(controls),
                     [w.shape for w in model.windows], model.q)
        return {"model": model.to_bundle()}


class AnalyzeEigenfeatures(SequenceStage):
    """Runtime: per frame the eigenfeature scores of the patches cut through the frame's
    similarity, with the head rotation, give the animation parameters (mu = L lambda), and the
    parameters the geometry of all layout points: in the neutral's frame (``displacements``, no
    head motion) and in the frame through its similarity (``points``; a 2D model, so out-of-plane
    rotation is not in it). Points of a feature whose patch left the image are flagged invalid."""

    name = "analyze.eigenfeatures"
    version = "1"
    doc = "animation parameters and all layout points from eigenfeature scores (Valente & Dugelay)"
    inputs = {"frames": "frames", "similarity": "similarity", "pose": "pose", "model": "eigen_model"}
    optional_inputs = frozenset({"pose", "model"})
    outputs = {"points": "points", "displacements": "displacements", "parameters": "eigen_parameters"}
    params = (
        Param("model_file", str, "", "a trained model (.npz of train.eigenfeatures) instead of the model input",
              file=True),
        Param("rotation", bool, True, "head rotation from the pose input in the estimator's observation (paper)"),
        Param("ridge", float, 0.0, "ridge of the estimator on standardized observations (0: the paper's least squares)",
              min=0.0),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        model = self.model(inputs, params)
        sim = inputs["similarity"]
        for key in ("params", "valid"):
            if key not in sim:
                raise StageError(f"{self.name}: input 'similarity' has no field '{key}'")
        frames: FrameStream = inputs["frames"]
        similarity = np.asarray(sim["params"], dtype=np.float64)
        T = len(similarity)
        if frames.info.frames != T:
            raise StageError(f"{self.name}: input 'similarity' has {T} frames, input 'frames' {frames.info.frames}")
        valid = np.asarray(sim["valid"], dtype=bool).copy()
        angles = None
        if params["rotation"]:
            pose = inputs.get("pose")
            if pose is None or "R" not in pose or "valid" not in pose:
                raise StageError(f"{self.name}: rotation=true needs the input 'pose' with fields 'R' and 'valid' "
                                 "(or set rotation=false)")
            if len(pose["R"]) != T:
                raise StageError(f"{self.name}: input 'pose' field 'R' has {len(pose['R'])} frames, expected {T}")
            angles = rotation_angles(pose["R"])
            valid &= np.asarray(pose["valid"], dtype=bool)
        mu, feature_valid = analyze_frames(model, _frames(frames, ctx), similarity, valid, angles,
                                           ridge=float(params["ridge"]))
        read = ~np.isnan(mu).any(axis=1)
        expression = parameters_to_points(model, np.where(read[:, None], mu, 0.0))
        xy = parameters_to_points(model, np.where(read[:, None], mu, 0.0), similarity)
        point_valid = np.repeat(read[:, None], len(model.point_names), axis=1)
        for j, window in enumerate(model.windows):
            point_valid[np.ix_(~feature_valid[:, j], list(window.points))] = False
        names = np.array(model.point_names, dtype=str)
        points = {"xy": xy, "valid": point_valid, "names": names}
        displacements = {"d": expression - model.neutral[None], "valid": point_valid, "names": names,
                         "neutral": model.neutral.copy()}
        for scalar in ("fps", "size"):
            if scalar in sim:
                points[scalar] = displacements[scalar] = np.asarray(sim[scalar])
        parameters = {"params": mu, "names": np.array(model.param_names, dtype=str), "valid": read,
                      "feature_valid": feature_valid,
                      "feature_names": np.array([w.name for w in model.windows], dtype=str)}
        return {"points": points, "displacements": displacements, "parameters": parameters}

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
