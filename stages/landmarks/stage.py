"""Stages ``landmarks.mediapipe`` (face mesh per frame) and ``landmarks.layout`` (the layout's
feature points from the mesh)."""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from runner.stage import Context, Param, SequenceStage, StageError
from stages.geometry.bundles import POINTS
from stages.landmarks.bundles import LANDMARKS
from stages.landmarks.correspondence import Correspondence, layout_from_mesh, load_correspondence
from stages.landmarks.landmarker import BLENDSHAPE_NAMES, N_MESH, SELECT_RULES, Landmarker
from stages.layout import Layout, load_layout


def _params(stage: SequenceStage, params: Mapping[str, Any]) -> dict[str, Any]:
    return {p.name: p.default for p in stage.params} | dict(params)


def layout_and_correspondence(stage: str, params: Mapping[str, Any]) -> tuple[Layout, Correspondence]:
    """The layout and mesh correspondence named by a stage's ``layout`` and ``correspondence``
    parameters; a bad correspondence is a :class:`StageError` naming the stage and parameter."""
    layout = load_layout(params["layout"])
    try:
        return layout, load_correspondence(params["correspondence"], layout=layout)
    except ValueError as exc:
        raise StageError(f"{stage}: parameter 'correspondence': {exc}") from None


class FaceLandmarks(SequenceStage):
    """``landmarks.mediapipe``: MediaPipe's 478-vertex face mesh, blendshapes and facial
    transformation matrix per frame (``stages.landmarks.landmarker``).

    Output bundle ``landmarks``: ``xy (T, 478, 2) f8`` px (project convention; NaN where no
    face), ``z (T, 478) f8`` relative depth in px, ``valid (T,) bool``, ``blendshapes (T, 52) f4``,
    ``blendshape_names (52,) str``, ``matrix (T, 4, 4) f8`` (identity where no face),
    ``face_width_px (T,) f8`` (width of the mesh's bounding box, cheek to cheek; NaN where no
    face), ``faces (T,) i8`` (faces found in the searched region), ``region (T, 4) i8``
    (``x0, y0, w, h`` of the crop, frame or tile the face was found in), ``fps ()``,
    ``size (2,)`` = (W, H).
    """

    name = "landmarks.mediapipe"
    version = "2"
    doc = "MediaPipe Face Landmarker: 478-point face mesh, 52 blendshapes and head matrix per frame"
    inputs = {"frames": "frames"}
    outputs = {"landmarks": LANDMARKS}
    params = (
        Param("max_faces", int, 4, "faces looked for per searched region", min=1, max=16),
        Param("select", str, "largest", "face chosen when there are several (then followed)", choices=SELECT_RULES),
        Param("min_detection_confidence", float, 0.5, "face detector score threshold", min=0.0, max=1.0),
        Param("crop_scale", float, 3.0, "crop around the previous face, x its box side (0 = off)", min=0.0, max=20.0),
        Param("search_tiles", bool, True, "search half-size tiles when the frame has no face"),
        Param("min_face_px", float, 60.0, "warn when a face is narrower than this (px)", min=0.0, max=10000.0),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        params = _params(self, params)
        stream = inputs["frames"]
        info = stream.info
        n = info.frames
        xy = np.full((n, N_MESH, 2), np.nan)
        z = np.full((n, N_MESH), np.nan)
        valid = np.zeros(n, bool)
        blendshapes = np.zeros((n, len(BLENDSHAPE_NAMES)), np.float32)
        matrix = np.tile(np.eye(4), (n, 1, 1))
        faces = np.zeros(n, np.int64)
        region = np.zeros((n, 4), np.int64)
        try:
            landmarker = Landmarker(
                max_faces=int(params["max_faces"]),
                select=str(params["select"]),
                min_detection_confidence=float(params["min_detection_confidence"]),
                crop_scale=float(params["crop_scale"]),
                search_tiles=bool(params["search_tiles"]),
            )
        except ValueError as exc:
            raise StageError(f"{self.name}: {exc}") from None
        with landmarker:
            for start, chunk in stream.chunks():
                if chunk.ndim != 4 or chunk.shape[3] != 3 or chunk.dtype != np.uint8:
                    raise StageError(
                        f"{self.name}: input 'frames': expected (H, W, 3) uint8 RGB frames, got {chunk.shape[1:]} {chunk.dtype}"
                    )
                for k, rgb in enumerate(chunk):
                    t = start + k
                    mesh = landmarker.detect(rgb)
                    xy[t], z[t], valid[t], blendshapes[t] = mesh.xy, mesh.z, mesh.valid, mesh.blendshapes
                    matrix[t], faces[t], region[t] = mesh.matrix, mesh.faces, mesh.region
                ctx.progress(len(chunk))
        if not valid.any():
            raise StageError(f"{self.name}: no face found in any of {n} frames of the input clip ({info.width}x{info.height})")
        width = np.full(n, np.nan)
        width[valid] = np.ptp(xy[valid, :, 0], axis=1)
        several = int((faces > 1).sum())
        ctx.log.info(
            "%s: face in %d of %d frames (%d without), several faces in %d frames; face width median %.0f px",
            self.name,
            int(valid.sum()),
            n,
            int((~valid).sum()),
            several,
            float(np.nanmedian(width)),
        )
        small = valid & (width < float(params["min_face_px"]))
        if small.any():
            ctx.log.warning(
                "%s: face narrower than %.0f px in %d frames (smallest %.1f px at frame %d): landmarks are less precise",
                self.name,
                float(params["min_face_px"]),
                int(small.sum()),
                float(np.nanmin(width)),
                int(np.nanargmin(width)),
            )
        return {
            "landmarks": {
                "xy": xy,
                "z": z,
                "valid": valid,
                "blendshapes": blendshapes,
                "blendshape_names": np.array(BLENDSHAPE_NAMES),
                "matrix": matrix,
                "face_width_px": width,
                "faces": faces,
                "region": region,
                "fps": np.float64(info.fps),
                "size": np.array([info.width, info.height], np.int64),
            }
        }


class LayoutPoints(SequenceStage):
    """``landmarks.layout``: the layout's feature points from the face mesh
    (:func:`stages.landmarks.correspondence.layout_from_mesh`).

    Output bundle ``points``: ``xy (T, N, 2) f8`` px, ``valid (T, N) bool`` (the frame's face was
    found), ``names (N,) str``, ``confidence (T, N) f4`` (1 where valid, 0 elsewhere: MediaPipe
    gives no per-point confidence), ``z (T, N) f8`` the points' depth (px, same combination of
    the vertices' ``z``) when the landmarks carry it, and ``fps``, ``size`` passed through.
    """

    name = "landmarks.layout"
    version = "1"
    doc = "The layout's feature points (zhang134) as fixed combinations of face-mesh vertices"
    inputs = {"landmarks": LANDMARKS}
    outputs = {"points": POINTS}
    params = (
        Param("layout", str, "zhang134", "layout name or YAML path", file=True),
        Param("correspondence", str, "zhang134_mediapipe", "mesh correspondence name or YAML path", file=True),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        params = _params(self, params)
        layout, correspondence = layout_and_correspondence(self.name, params)
        bundle = inputs["landmarks"]
        for key in ("xy", "valid"):
            if key not in bundle:
                raise StageError(f"{self.name}: input 'landmarks': missing key '{key}'")
        try:
            xy = layout_from_mesh(bundle["xy"], correspondence)
        except ValueError as exc:
            raise StageError(f"{self.name}: input 'landmarks' field 'xy': {exc}") from None
        valid = np.broadcast_to(np.asarray(bundle["valid"], bool)[:, None], xy.shape[:2]).copy()
        out = {"xy": xy, "valid": valid, "names": np.array(layout.point_names), "confidence": valid.astype(np.float32)}
        if "z" in bundle:  # the depth of each layout point, same combination of vertices (px)
            out["z"] = layout_from_mesh(np.asarray(bundle["z"])[..., None], correspondence)[..., 0]
        out.update({k: np.asarray(bundle[k]) for k in ("fps", "size") if k in bundle})
        ctx.progress(len(xy))
        return {"points": out}
