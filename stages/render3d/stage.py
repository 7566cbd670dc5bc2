"""Stages ``render3d.head`` (the performer's head pose on the target mesh) and ``render3d`` (Sec. 14.1).

``render3d.head`` reads the pack's geometry, generic 3D model and camera (the target's depth and
head centre, :func:`stages.mesh3d.model.target_depth`) and the performer's pose; output bundle
``head3d``: ``R (T, 3, 3)``, ``t (T, 3)`` mm — the rigid motion ``X' = R X + t`` of the target's 3D
model in the target camera's frame (:mod:`stages.render3d.head`), the one the 3D render and the
2D result's depth-aware head turn (``synthesis.synthesize``, :mod:`stages.synthesis.turn`) both
apply; ``valid (T,)`` (frames without a valid pose keep the reference pose); ``ypr_deg (T, 3)`` of
``R`` (``R = Ry Rx Rz``, degrees); ``pivot (3,)`` mm; ``depth (N,)`` mm, the camera depth of each
layout point ``names (N,)`` at the neutral; ``camera (3, 3)``, ``size (2,)`` the pack camera. With
the ``landmarks`` input (and ``absolute``), the reference frame's own rotation is composed in:
``R = R_rel R_ref`` (the pack's target is frontal).

``render3d`` renders each frame's Sec. 9 mesh (``mesh3d.synthesize``), moved by the head motion
and textured with the frame's synthesized image (``synthesis.synthesize`` without head motion:
the expression in the target's own frame, whose feature points are the mesh's ``uv``).

With the whole head (a ``mesh3d`` bundle made with the synthesis model: face, hair, ears, neck and
the background, :mod:`stages.synthesis.surround`) every vertex moves by the head's motion weighted
as in the 2D result's head turn (``X'' = w (R X + t) + (1 - w) X``), so the render is the whole
frame at the 2D result's place; the texture is looked up projectively (the frame's synthesized
image is the view of the mesh at rest: at rest the render reproduces it). A second colour pass
renders the mattes (face, head, validity) over the same mesh. Outputs: ``frames`` sRGB (the whole
frame), ``mask`` the face matte, ``head_matte``, ``filled`` (1 - the rendered validity: pixels no
real source covers, and those no triangle covers), ``depth`` camera depth in mm, and ``exr``:
``frame.%06d.exr`` with the shot channels of ``write.exr`` (the head with associated alpha, the
plate, ``face.A``, ``filled.A``) and ``Z``.

With a face-only mesh (no synthesis model): ``frames`` sRGB over black, ``mask`` alpha (MSAA
coverage x the synthesized face mask), ``head_matte`` the coverage, ``filled`` 0, ``depth``, and
``exr`` RGBA + Z.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from runner.stage import Context, FrameStage, Param, SequenceStage, StageError, StreamInfo
from stages.geometry.bundles import DISPLACEMENTS, HEAD_POSE_RELATIVE
from stages.landmarks.bundles import LANDMARKS
from stages.mesh3d.bundles import MESH3D
from stages.pack.bundle_types import CAMERA, PACK_GEOMETRY, PACK_MODEL3D
from stages.render3d.bundles import HEAD3D
from stages.geometry.rotation import landmarker_rotation, ypr_yxz
from stages.mesh3d.model import target_depth
from stages.mesh3d.stage import GEOMETRY, mesh_vertices
from stages.pack.bundles import camera_from_bundle, geometry_from_bundle, model3d_from_bundle
from stages.render3d.frame import render_textured, scaled_intrinsics, to_display
from stages.render3d.head import apply_head, head_motion_3d
from stages.render3d.raster import MeshRenderer
from stages.synthesis.synthesize import head_motion_frame
from stages.color import srgb_to_linear, to_unit_float
from stages.writers.exr import exr_name, frame_attributes, head_attributes, linear_shot_channels, write_exr


def _field(bundle: Mapping[str, np.ndarray], key: str, stage: str, port: str) -> np.ndarray:
    if key not in bundle:
        raise StageError(f"{stage}: input '{port}' has no field '{key}'")
    return np.asarray(bundle[key])


def behind_the_lips(vertices: np.ndarray, names: np.ndarray) -> np.ndarray:
    """``vertices (N, 3)`` mm with the teeth points (``teeth_*``) moved ``MOUTH_BEHIND_MM`` farther
    along their rays: the mouth opening behind the lips that close over it (the 2D warp's painting
    order, :mod:`stages.synthesis.turn`); at rest they project where they did."""
    from stages.mesh3d.model import skin_points
    from stages.synthesis.turn import MOUTH_BEHIND_MM

    out = np.array(vertices, np.float64)
    teeth = ~skin_points(names)
    out[teeth] *= (1.0 + MOUTH_BEHIND_MM / out[teeth, 2])[:, None]
    return out


class HeadPose3D(SequenceStage):
    """``render3d.head``: the performer's relative head pose as a rigid motion of the target mesh."""

    name = "render3d.head"
    version = "3"
    doc = "Sec. 14.1: performer head pose (compensate.rigid3d) -> rigid motion of the target's 3D model, mm; point depths"
    inputs = {
        "geometry": PACK_GEOMETRY,
        "model3d": PACK_MODEL3D,
        "camera": CAMERA,
        "pose": HEAD_POSE_RELATIVE,
        "performer": DISPLACEMENTS,
        "landmarks": LANDMARKS,
    }
    optional_inputs = frozenset({"performer", "landmarks"})
    outputs = {"head": HEAD3D}
    params = (
        Param(
            "translation_scale",
            float,
            1.0,
            "multiplies the carried head translation (after the face-size ratio)",
            min=0.0,
            max=100.0,
        ),
        Param(
            "absolute",
            bool,
            True,
            "with 'landmarks': compose the reference frame's own head rotation (the landmarker's "
            "matrix), so the frontal target turns as the performer does, not relative to a turned reference",
        ),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        pose = inputs["pose"]
        try:
            geometry = geometry_from_bundle(inputs["geometry"])
            model3d = model3d_from_bundle(inputs["model3d"], geometry.names)
            A = camera_from_bundle(inputs["camera"], size=geometry.size)
            names = np.array(geometry.names)
            depth, pivot, _, _ = target_depth(model3d, geometry.neutral, A, names)
        except ValueError as exc:
            raise StageError(f"{self.name}: {exc}") from None
        R = _field(pose, "R", self.name, "pose").astype(np.float64)
        tvec = _field(pose, "tvec", self.name, "pose").astype(np.float64)
        scale = np.asarray(pose["scale"], np.float64)
        T = len(R)
        valid = np.asarray(pose["valid"], bool) if "valid" in pose else np.ones(T, bool)
        valid &= np.isfinite(R).all((1, 2)) & np.isfinite(tvec).all(1) & np.isfinite(scale) & (scale > 0)
        R, tvec, scale = R.copy(), tvec.copy(), scale.copy()
        R[~valid], tvec[~valid], scale[~valid] = np.eye(3), 0.0, 1.0
        marks = inputs.get("landmarks")
        reference = np.eye(3)
        if marks is not None and params["absolute"]:
            frame = int(_field(pose, "neutral_frame", self.name, "pose"))
            matrix = _field(marks, "matrix", self.name, "landmarks")
            if not 0 <= frame < len(matrix):
                raise StageError(
                    f"{self.name}: the pose's neutral_frame {frame} is outside the {len(matrix)} frames of 'landmarks'"
                )
            reference = landmarker_rotation(matrix[frame])
        target_2d = geometry.neutral  # the lifted neutral reprojects onto it exactly
        performer = inputs.get("performer")
        if performer is not None:
            for key in ("neutral", "names"):
                _field(performer, key, self.name, "performer")
            center, _, ratio = head_motion_frame(performer["neutral"], performer["names"], target_2d, names)
        else:
            center, ratio = target_2d.mean(0), 1.0
        try:
            rotation, translation = head_motion_3d(
                R,
                tvec,
                scale,
                source_center=center,
                pivot=pivot,
                A=A,
                size_ratio=ratio * float(params["translation_scale"]),
                reference=reference,
            )
        except ValueError as exc:
            raise StageError(f"{self.name}: input 'pose': {exc}") from None
        out = {
            "R": rotation,
            "t": translation,
            "valid": valid,
            "pivot": pivot,
            "depth": depth,
            "names": names,
            "camera": A,
            "size": np.array(geometry.size, np.int64),
        }
        out["ypr_deg"] = ypr_yxz(rotation)
        ctx.progress(T)
        return {"head": out}


class Render3D(FrameStage):
    """``render3d``: the textured target mesh under the performer's head pose (Sec. 14.1)."""

    name = "render3d"
    version = "2"
    doc = "Sec. 14.1: Sec. 9 mesh (the whole head) + synthesized texture under the head pose; z-buffer, MSAA, mattes, depth; EXR"
    inputs = {
        "texture": "frames",
        "mask": "frames",
        "head_matte": "frames",
        "filled": "frames",
        "mesh": MESH3D,
        "head": HEAD3D,
    }
    optional_inputs = frozenset({"mask", "head_matte", "filled", "head"})
    outputs = {
        "frames": "frames",
        "mask": "frames",
        "head_matte": "frames",
        "filled": "frames",
        "depth": "frames",
        "exr": "files",
    }
    params = (
        Param("samples", int, 4, "MSAA samples per pixel (anti-aliased edges; 0 = none); at most the driver's", min=0, max=16),
        Param("resolution_scale", float, 1.0, "output size = the pack image size times this", min=0.25, max=8.0),
        GEOMETRY,
        Param("compression", str, "zip", "lossless EXR compression", choices=("zip", "zips", "piz", "rle", "none")),
    )

    # One renderer (GL context) for the run, made in open and released in close: a GL context is
    # current on one thread at a time, so the runner calls process one chunk at a time (from
    # whichever producer thread), and process makes the context current for each frame.
    threading = "single"

    def __init__(self) -> None:
        self._renderer: MeshRenderer | None = None

    def _size(self, mesh: Mapping[str, np.ndarray], params: Mapping[str, Any]) -> tuple[int, int]:
        W, H = (int(v) for v in mesh["size"])
        s = float(params["resolution_scale"])
        return max(round(W * s), 1), max(round(H * s), 1)

    def stream_info(self, inputs: Mapping[str, Any], params: Mapping[str, Any]) -> StreamInfo:
        info = inputs["texture"].info
        W, H = self._size(inputs["mesh"], params)
        return StreamInfo(frames=info.frames, fps=info.fps, width=W, height=H)

    def open(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> None:
        """Make the renderer (a headless GL context) for the output size and ``samples``."""
        try:
            self._renderer = MeshRenderer(self._size(inputs["mesh"], params), samples=int(params["samples"]))
        except RuntimeError as exc:
            raise StageError(f"{self.name}: {exc}") from None
        with self._renderer.ctx:  # made current on this thread; leaving it frees it for the thread calling process
            pass

    def close(self, ctx: Context) -> None:
        """Release the renderer's GL context (moderngl does not when it is collected)."""
        if self._renderer is not None:
            self._renderer.release()
            self._renderer = None

    def process(
        self, start: int, stop: int, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context
    ) -> dict[str, Any]:
        mesh, head, stream = inputs["mesh"], inputs.get("head"), inputs["texture"]
        vertices = mesh_vertices(mesh, params["geometry"], stage=self.name)
        if len(vertices) != stream.info.frames or (head is not None and len(head["R"]) != stream.info.frames):
            raise StageError(f"{self.name}: inputs 'mesh'/'head' do not have the {stream.info.frames} frames of 'texture'")
        textures = stream.read(start, stop)
        planes = {
            port: inputs[port].read(start, stop) for port in ("mask", "head_matte", "filled") if inputs.get(port) is not None
        }
        whole = "head_triangles" in mesh
        renderer = self._renderer
        if renderer is None:
            raise RuntimeError(f"{self.name}: process before open (runner.lifecycle.opened)")
        A = scaled_intrinsics(mesh["camera"], float(params["resolution_scale"]))
        folder = ctx.files_dir("exr")
        folder.mkdir(parents=True, exist_ok=True)
        out: dict[str, list[np.ndarray]] = {k: [] for k in ("frames", "mask", "head_matte", "filled", "depth")}
        for i, frame in enumerate(range(start, stop)):
            v, uv = np.asarray(vertices[frame], np.float64), np.asarray(mesh["uv"][frame], np.float64)
            triangles, weight = mesh["triangles"], None
            if whole:
                v = np.concatenate([behind_the_lips(v, mesh["names"]), mesh["surround"]])
                uv = np.concatenate([uv, mesh["surround_uv"]])
                triangles, weight = mesh["head_triangles"], np.asarray(mesh["weight"], np.float64)[:, None]
            rest = v
            attrs = frame_attributes(frame, fps=stream.info.fps)
            if head is not None:
                moved = apply_head(v, np.asarray(head["R"][frame]), np.asarray(head["t"][frame]))
                v = moved if weight is None else weight * moved + (1.0 - weight) * v
                attrs.update(head_attributes(head, frame))
            mattes = {port: planes[port][i] for port in planes}
            with renderer.ctx:  # current on this thread for this frame
                if whole:
                    rendered = self._render_whole(renderer, v, triangles, uv, rest[:, 2], textures[i], mattes, A)
                else:
                    rendered = self._render_face(renderer, v, triangles, uv, textures[i], mattes.get("mask"), A)
            (rgba, layers), planes_out = rendered
            write_exr(
                folder / exr_name(frame),
                rgba,
                attributes=attrs,
                compression=params["compression"],
                depth=planes_out["depth"],
                layers=layers,
            )
            for key in out:
                out[key].append(planes_out[key] if key != "depth" else planes_out[key][..., None])
        ctx.progress(stop - start)
        return {**{k: np.stack(v).astype(np.float32 if k == "depth" else np.float16) for k, v in out.items()}, "exr": None}

    @staticmethod
    def _render_face(
        renderer: MeshRenderer,
        v: np.ndarray,
        triangles: np.ndarray,
        uv: np.ndarray,
        texture: np.ndarray,
        mask: np.ndarray | None,
        A: np.ndarray,
    ) -> tuple[tuple[np.ndarray, None], dict[str, np.ndarray]]:
        """The face-only mesh: premultiplied RGBA over black (alpha = coverage x face mask)."""
        rgba, depth = render_textured(renderer, v, triangles, uv, texture, A, mask=mask)
        rgb, alpha = to_display(rgba)
        return (rgba, None), {"frames": rgb, "mask": alpha, "head_matte": alpha, "filled": np.zeros_like(alpha), "depth": depth}

    @staticmethod
    def _render_whole(
        renderer: MeshRenderer,
        v: np.ndarray,
        triangles: np.ndarray,
        uv: np.ndarray,
        rest_depth: np.ndarray,
        texture: np.ndarray,
        mattes: Mapping[str, np.ndarray],
        A: np.ndarray,
    ) -> tuple[tuple[np.ndarray, dict[str, np.ndarray]], dict[str, np.ndarray]]:
        """The whole head: the plate and the mattes rendered over one mesh; the shot channels."""
        h, w = texture.shape[:2]
        colour = srgb_to_linear(to_unit_float(np.asarray(texture)).astype(np.float32))
        ones = np.ones((h, w), np.float32)

        def matte(port: str, default: np.ndarray) -> np.ndarray:
            return np.asarray(mattes[port], np.float32).reshape(h, w) if port in mattes else default

        matte_texture = np.stack([matte("mask", ones), matte("head_matte", ones), 1.0 - matte("filled", 0 * ones), ones], -1)
        (plate, rendered), depth = renderer.render(v, triangles, uv, (colour, matte_texture), A, uv_depth=rest_depth)
        linear = np.moveaxis(plate[..., :3], -1, 0)  # premultiplied by coverage: 1 wherever the mesh is
        face, head_matte = np.clip(rendered[..., 0], 0, 1), np.clip(rendered[..., 1], 0, 1)
        filled = np.clip(1.0 - rendered[..., 2], 0, 1)
        channels = linear_shot_channels(linear, head_matte, face, filled)
        rgb, _ = to_display(plate)
        return channels, {
            "frames": rgb,
            "mask": face[..., None],
            "head_matte": head_matte[..., None],
            "filled": filled[..., None],
            "depth": depth,
        }
