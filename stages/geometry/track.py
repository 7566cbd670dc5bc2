"""Feature point tracking in a performer clip (paper Sec. 14.1: "correlation-based tracking").

The default tracker (``method="ncc"``) follows each point of the tracked subset with normalized
cross-correlation (NCC) of a small template inside a search window centred on a constant-velocity
prediction and controls drift by matching the first-frame template (the anchor), warped by the
point's local affine motion estimated from its neighbours, in the same window: where the anchor
matches well its peak wins, else the running template's. The peak is refined to sub-pixel
precision by a parabola, then by inverse-compositional Lucas-Kanade; a point whose template pins
one direction only (an edge, e.g. the hairline) takes the other from its neighbours -- or, given
the performer pack, every point is pulled towards a 3D face model (generic shape plus the
performer's captured expressions) fitted to all matches each frame. Every point
in every frame gets a confidence (the final NCC). A point that is lost or leaves the frame is
flagged invalid, carried along by the similarity motion of the valid points, and keeps being
searched for; it is never dropped.

``method`` also selects OpenCV's correlation-filter trackers (``csrt``, ``kcf``, ``mosse``, one
tracker per point on a box around it) and pyramidal Lucas-Kanade with a forward-backward check
(``lk``), so that a benchmark can compare them on the same clip.

Frames are consumed one at a time from an iterable; a clip is never held in memory.

The stage, :class:`CorrelationTrack`, is here; the parts are modules of their own:
:mod:`~stages.geometry.tracking` (``track_points``, ``make_tracker``),
:mod:`~stages.geometry.ncc_tracker`, :mod:`~stages.geometry.baseline_trackers`,
:mod:`~stages.geometry.correlation` (the primitives), :mod:`~stages.geometry.first_frame_points`
and :mod:`~stages.geometry.tracker_options` (the one source of the defaults).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from runner.stage import Context, Param, SequenceStage, StageError
from stages.geometry.bundles import POINTS
from stages.pack.bundle_types import CAMERA, PACK_GEOMETRY, PACK_MODEL3D
from stages.geometry.face_model import FaceModel, bundle_face_model
from stages.geometry.first_frame_points import order_by_layout, read_first_frame_points
from stages.geometry.subset import rigid_columns
from stages.geometry.tracker_options import DEFAULTS, TrackerOptions
from stages.geometry.tracking import METHODS, track_points
from stages.layout import load_layout
from stages.pack.bundles import camera_from_bundle

FACE_MODEL_INPUTS = ("model3d", "geometry", "camera")  # pack.load's bundles of the performer pack


def iter_frames(stream: Any) -> Iterator[np.ndarray]:
    """Frames of a :class:`runner.stage.FrameStream`, one at a time, read chunk by chunk."""
    for _, chunk in stream.chunks():
        yield from chunk


class CorrelationTrack(SequenceStage):
    """``track.correlation``: the tracked subset of the layout through the performer clip.

    ``init`` is the first-frame points file of the tracked points (a ``file`` pipeline input:
    ``name,x,y`` CSV or JSON), read by :func:`read_first_frame_points` and checked against the
    layout's tracked subset and the frame size. ``model3d``, ``geometry`` and ``camera`` (optional,
    together: ``pack.load``'s bundles of the performer's actor pack) give the ``ncc`` tracker its
    face model (:func:`stages.geometry.face_model.bundle_face_model`: the pack's generic 3D model,
    captured expressions and intrinsics, which must be for the clip's frame size).
    """

    name = "track.correlation"
    version = "7"
    doc = "track the layout's tracked subset through a clip (NCC, or CSRT/KCF/MOSSE/LK)"
    inputs = {"frames": "frames", "init": "file", "model3d": PACK_MODEL3D, "geometry": PACK_GEOMETRY, "camera": CAMERA}
    optional_inputs = frozenset(FACE_MODEL_INPUTS)
    outputs = {"points": POINTS}
    params = (
        Param("layout", str, "zhang134", "layout name or YAML path; its `tracked` subset is followed", file=True),
        Param("method", str, "ncc", "tracker", choices=METHODS),
        Param(
            "template_px",
            int,
            DEFAULTS.template_px,
            "template side in px (LK window; OpenCV trackers' box is template+2*search)",
            min=3,
            max=255,
        ),
        Param(
            "search_px", int, DEFAULTS.search_px, "search radius in px around the constant-velocity prediction", min=1, max=255
        ),
        Param("min_score", float, DEFAULTS.min_score, "ncc: lowest peak NCC of a valid point", min=-1.0, max=1.0),
        Param(
            "min_psr",
            float,
            DEFAULTS.min_psr,
            "ncc: lowest peak-to-sidelobe ratio of a valid point (0 = off: NCC "
            "peaks on smooth skin are broad, so their PSR is low even when right)",
            min=0.0,
            max=1000.0,
        ),
        Param(
            "min_contrast",
            float,
            DEFAULTS.min_contrast,
            "ncc: lowest standard deviation (intensity levels) of a valid point's patch",
            min=0.0,
            max=255.0,
        ),
        Param(
            "anchor_score",
            float,
            DEFAULTS.anchor_score,
            "ncc: score of the warped first-frame template above which it is used instead of the running template",
            min=-1.0,
            max=1.0,
        ),
        Param(
            "warp_frac",
            float,
            DEFAULTS.warp_frac,
            "ncc: neighbourhood (Gaussian sigma) of the local affine motion "
            "that warps a point's first-frame template, as a fraction of the RMS spread of the points",
            min=0.0,
            max=10.0,
        ),
        Param(
            "lk_iterations",
            int,
            DEFAULTS.lk_iterations,
            "ncc: inverse-compositional Lucas-Kanade steps of the sub-pixel refinement",
            min=0,
            max=100,
        ),
        Param(
            "lk_sigma_px",
            float,
            DEFAULTS.lk_sigma_px,
            "ncc: Gaussian weight (sigma, px) of the template cells in "
            "the Lucas-Kanade refinement: the centre of a warped template is the least distorted",
            min=0.0,
            max=1000.0,
        ),
        Param(
            "prior",
            float,
            DEFAULTS.prior,
            "ncc without a pack: weight (1/px^2) of the neighbours' position against the template's own information (0 = off)",
            min=0.0,
            max=1e6,
        ),
        Param(
            "prior_frac",
            float,
            DEFAULTS.prior_frac,
            "ncc: neighbourhood (Gaussian sigma) of the neighbours' position, as a fraction of the RMS spread of the points",
            min=0.0,
            max=100.0,
        ),
        Param("fb_px", float, DEFAULTS.fb_px, "lk: largest forward-backward error of a valid point, px", min=0.0, max=1000.0),
        Param(
            "model_prior",
            float,
            DEFAULTS.model_prior,
            "ncc with a pack: weight (1/px^2) of the fitted face model's position against the template's own information",
            min=0.0,
            max=1e6,
        ),
        Param(
            "model_components",
            int,
            8,
            "ncc with a pack: expression components of the face model (PCA of the pack's captured geometries)",
            min=1,
            max=256,
        ),
        Param(
            "model_ridge",
            float,
            DEFAULTS.model_ridge,
            "ncc with a pack: weight of the prior keeping the expression coefficients within the captured set's spread",
            min=0.0,
            max=1e6,
        ),
        Param(
            "model_noise_px",
            float,
            DEFAULTS.model_noise_px,
            "ncc with a pack: reference match noise, px; a "
            "point whose running RMS distance to the fitted model is below it gains weight against the model "
            "(up to 4x), one above it loses weight",
            min=0.0,
            max=1000.0,
        ),
        Param(
            "model_noise_rate",
            float,
            DEFAULTS.model_noise_rate,
            "ncc with a pack: rate of the running mean of each point's squared distance to the fitted model (0 = fixed weights)",
            min=0.0,
            max=1.0,
        ),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        params = {p.name: p.default for p in self.params} | dict(params)
        stream = inputs["frames"]
        info = stream.info
        layout = load_layout(params["layout"])
        expected = tuple(layout.point_names[i] for i in layout.tracked)
        path = Path(inputs["init"])
        names, xy, frame_size = read_first_frame_points(path)
        init = order_by_layout(path, names, xy, expected, (info.width, info.height), frame_size)
        given = [port for port in FACE_MODEL_INPUTS if inputs.get(port) is not None]
        if given and len(given) < len(FACE_MODEL_INPUTS):
            raise StageError(
                f"{self.name}: the face model needs the inputs {', '.join(FACE_MODEL_INPUTS)} together "
                f"(pack.load's outputs), got only {', '.join(given)}"
            )
        face_model = None
        if given and params["method"] == "ncc":
            face_model = self.face_model(inputs, layout, init, (info.width, info.height), params["model_components"])
        try:
            tracks = track_points(
                iter_frames(stream),
                init,
                method=params["method"],
                options=TrackerOptions.of(params),
                face_model=face_model,
                progress=ctx.progress,
            )
        except ValueError as exc:
            raise StageError(f"{self.name}: {exc}") from None
        return {
            "points": {
                "xy": tracks.xy,
                "valid": tracks.valid,
                "confidence": tracks.confidence,
                "names": np.array(expected),
                "fps": np.array(info.fps, dtype=np.float64),
                "size": np.array([info.width, info.height], dtype=np.int64),
            }
        }

    def face_model(
        self, inputs: Mapping[str, Any], layout: Any, init: np.ndarray, size: tuple[int, int], components: int
    ) -> FaceModel:
        """The tracked points' face model from the performer pack's bundles (:func:`bundle_face_model`)."""
        names = [layout.point_names[i] for i in layout.tracked]
        rigid = rigid_columns(np.array(names), layout, at_least=4, stage=self.name)
        try:
            camera = camera_from_bundle(inputs["camera"], size=size)
            return bundle_face_model(inputs["model3d"], inputs["geometry"], names, init, rigid, camera, components=components)
        except ValueError as exc:
            raise StageError(f"{self.name}: {exc}") from None
