"""``write.usd``: the animated target mesh as a USD scene (usd-core), with its texture sequence.

Files written (under ``out/<stage>/``):

``scene.usda``
    ``/Root`` (Xform; the stage is Y-up, ``metersPerUnit = 0.001``: units are mm;
    ``timeCodesPerSecond`` = the clip's fps, time code = frame index) holding
    ``/Root/Head`` (Xform, the head motion as a time-sampled ``xformOp:transform``),
    ``/Root/Head/Face`` (Mesh: time-sampled ``points`` — the Sec. 9 vertices before head motion —,
    fixed ``faceVertexCounts``/``faceVertexIndices``, time-sampled ``primvars:st`` (vertex
    interpolation: each vertex's position in that frame's texture), bound to
    ``/Root/Materials/Face`` (UsdPreviewSurface whose ``diffuseColor`` and ``opacity`` come from a
    UsdUVTexture with a time-sampled ``inputs:file``, one PNG per frame)) and ``/Root/Camera``
    (the target camera: intrinsics as focal length and apertures, at the origin looking down -Z).
``/Root/Surround`` (Mesh, with the whole head: ``mesh3d.synthesize`` given the synthesis model)
    The part of the whole head that does not move rigidly with it: the band from the head ring to
    the outer ring and the image's edge, and the background beyond. Its ``points`` are
    time-sampled *after* the head's motion (weighted per vertex as in the 2D result: ``w (R X + t)
    + (1 - w) X``), in the camera frame, so it is not under ``/Root/Head``; it shares the face's
    material and its ``primvars:st``. ``/Root/Head/Face`` then holds the triangles whose vertices
    all follow the head (face, teeth, head ring): feature points and anchors alike.
``textures/texture.%06d.png``
    The synthesized expression image of each frame, RGBA (alpha = the synthesized face mask).
``head_pose.csv``
    Per frame: ``frame, time_s, valid, R00..R22, tx_mm, ty_mm, tz_mm`` (and ``yaw_deg, pitch_deg,
    roll_deg`` when known): the rigid motion ``X' = R X + t`` of the mesh, target camera frame.

Axes: the pipeline's camera frame (x right, y down, z away from the camera) is turned 180 degrees
about x into USD's Y-up frame (``(x, y, z) -> (x, -y, -z)``); triangle order is reversed so that
front faces wind counter-clockwise as seen from the camera (USD's ``rightHanded`` orientation).
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from runner.stage import Context, Param, SequenceStage, StageError
from stages.mesh3d.bundles import MESH3D
from stages.render3d.bundles import HEAD3D
from stages.color import to_uint8
from stages.mesh3d.stage import GEOMETRY, mesh_vertices

__all__ = ["FLIP", "write_usd_scene", "WriteUsd"]

FLIP = np.diag([1.0, -1.0, -1.0])  # pipeline camera frame -> USD Y-up frame (a rotation by pi about x)
TEXTURE_NAME = "textures/texture.{:06d}.png"


def _matrix(R: np.ndarray, t: np.ndarray):
    """USD row-vector 4x4 of ``X' = FLIP (R FLIP X + t)`` (the motion expressed in the USD frame)."""
    from pxr import Gf

    M = np.eye(4)
    M[:3, :3] = (FLIP @ R @ FLIP).T
    M[3, :3] = FLIP @ t
    return Gf.Matrix4d(M.tolist())


def write_usd_scene(
    path: Path,
    *,
    vertices: np.ndarray,
    triangles: np.ndarray,
    uv: np.ndarray,
    size: tuple[int, int],
    camera: np.ndarray,
    fps: float,
    head_R: np.ndarray | None = None,
    head_t: np.ndarray | None = None,
    texture_files: list[str] | None = None,
    surround_triangles: np.ndarray | None = None,
    surround_points: np.ndarray | None = None,
) -> None:
    """Write the animated mesh as a USD layer (``.usda`` text or ``.usdc`` by the suffix).

    Parameters
    ----------
    path : the layer file
    vertices : (T, V, 3) float, mm, camera frame before head motion
    triangles : (F, 3) int, counter-clockwise on screen (y down)
    uv : (T, V, 2) float, texture px of each vertex per frame
    size : (W, H) of the texture images, px
    camera : (3, 3) intrinsics, px
    fps : frames per second (time code = frame index)
    head_R, head_t : (T, 3, 3), (T, 3) mm, optional head motion ``X' = R X + t``
    texture_files : T paths relative to the layer, optional
    surround_triangles : (G, 3) int, optional
        Triangles of ``/Root/Surround`` (module docstring), over the same vertices.
    surround_points : (T, V, 3) float, mm, optional
        The vertices after the head's motion, camera frame (with ``surround_triangles``).
    """
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade

    vertices = np.asarray(vertices, np.float64)
    T = len(vertices)
    W, H = size
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(max(T - 1, 0))
    stage.SetTimeCodesPerSecond(float(fps))
    stage.SetFramesPerSecond(float(fps))
    root = UsdGeom.Xform.Define(stage, "/Root")
    stage.SetDefaultPrim(root.GetPrim())
    head = UsdGeom.Xform.Define(stage, "/Root/Head")
    op = head.AddTransformOp()
    if head_R is not None and head_t is not None:
        for f in range(T):
            op.Set(_matrix(np.asarray(head_R[f], np.float64), np.asarray(head_t[f], np.float64)), Usd.TimeCode(f))
    else:
        op.Set(Gf.Matrix4d(1.0))
    uv = np.asarray(uv, np.float64)
    st_all = np.stack([(uv[..., 0] + 0.5) / W, 1.0 - (uv[..., 1] + 0.5) / H], axis=-1)
    meshes = [_mesh(stage, "/Root/Head/Face", vertices, triangles, st_all)]
    if surround_triangles is not None and len(surround_triangles):
        meshes.append(_mesh(stage, "/Root/Surround", np.asarray(surround_points, np.float64), surround_triangles, st_all))
    if texture_files is not None:
        material = UsdShade.Material.Define(stage, "/Root/Materials/Face")
        shader = UsdShade.Shader.Define(stage, "/Root/Materials/Face/Surface")
        shader.CreateIdAttr("UsdPreviewSurface")
        reader = UsdShade.Shader.Define(stage, "/Root/Materials/Face/st")
        reader.CreateIdAttr("UsdPrimvarReader_float2")
        reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")  # UsdPrimvarReader: string (Sdr)
        tex = UsdShade.Shader.Define(stage, "/Root/Materials/Face/Texture")
        tex.CreateIdAttr("UsdUVTexture")
        tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
        file_in = tex.CreateInput("file", Sdf.ValueTypeNames.Asset)
        for f, name in enumerate(texture_files):
            file_in.Set(Sdf.AssetPath(name), Usd.TimeCode(f))
        tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("sRGB")
        rgb = tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
        alpha = tex.CreateOutput("a", Sdf.ValueTypeNames.Float)
        shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(rgb)
        shader.CreateInput("opacity", Sdf.ValueTypeNames.Float).ConnectToSource(alpha)
        shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.8)
        material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
        for mesh in meshes:
            UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    A = np.asarray(camera, np.float64)
    cam = UsdGeom.Camera.Define(stage, "/Root/Camera")
    focal = 50.0  # mm; the apertures carry the field of view
    cam.CreateFocalLengthAttr(focal)
    cam.CreateHorizontalApertureAttr(float(W / A[0, 0] * focal))
    cam.CreateVerticalApertureAttr(float(H / A[1, 1] * focal))
    cam.CreateHorizontalApertureOffsetAttr(float(((W - 1) / 2.0 - A[0, 2]) / A[0, 0] * focal))
    cam.CreateVerticalApertureOffsetAttr(float((A[1, 2] - (H - 1) / 2.0) / A[1, 1] * focal))
    cam.CreateClippingRangeAttr(Gf.Vec2f(10.0, 100000.0))
    stage.GetRootLayer().Save()


def _mesh(stage, path: str, vertices: np.ndarray, triangles: np.ndarray, st: np.ndarray):
    """A triangle mesh at ``path`` with time-sampled ``points`` (``vertices (T, V, 3)`` mm, pipeline
    camera axes) and vertex ``primvars:st`` (``st (T, V, 2)``), front faces counter-clockwise."""
    from pxr import Gf, Sdf, Usd, UsdGeom, Vt

    mesh = UsdGeom.Mesh.Define(stage, path)
    tri = np.asarray(triangles, np.int64)[:, [0, 2, 1]]
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(tri)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(tri.ravel().tolist()))
    mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    points = mesh.CreatePointsAttr()
    primvar = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
    for f in range(len(vertices)):
        points.Set(Vt.Vec3fArray.FromNumpy((vertices[f] @ FLIP).astype(np.float32)), Usd.TimeCode(f))
        primvar.Set(Vt.Vec2fArray.FromNumpy(st[f].astype(np.float32)), Usd.TimeCode(f))
    lo, hi = (vertices @ FLIP).min((0, 1)), (vertices @ FLIP).max((0, 1))
    mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*lo.tolist()), Gf.Vec3f(*hi.tolist())]))
    return mesh


def write_pose_csv(path: Path, head: Mapping[str, np.ndarray], *, fps: float) -> None:
    """The per-frame head motion as CSV (columns in the module docstring)."""
    R = np.asarray(head["R"], np.float64)
    t = np.asarray(head["t"], np.float64)
    valid = np.asarray(head.get("valid", np.ones(len(R), bool)), bool)
    ypr = np.asarray(head["ypr_deg"], np.float64) if "ypr_deg" in head else None
    header = ["frame", "time_s", "valid", *[f"R{i}{j}" for i in range(3) for j in range(3)], "tx_mm", "ty_mm", "tz_mm"]
    header += ["yaw_deg", "pitch_deg", "roll_deg"] if ypr is not None else []
    with path.open("w", newline="", encoding="utf-8") as fh:
        out = csv.writer(fh)
        out.writerow(header)
        for f in range(len(R)):
            row = [f, f"{f / fps:.6f}", int(valid[f]), *[f"{v:.9g}" for v in R[f].ravel()], *[f"{v:.6f}" for v in t[f]]]
            row += [f"{v:.4f}" for v in ypr[f]] if ypr is not None else []
            out.writerow(row)


def whole_head_parts(
    mesh: Mapping[str, np.ndarray], vertices: np.ndarray, head: Mapping[str, np.ndarray] | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """The whole head of a ``mesh3d`` bundle split as the scene holds it (module docstring).

    Returns
    -------
    vertices : (T, N + A, 3) mm, at rest; uv : (T, N + A, 2) px; rigid : (F, 3) the triangles whose
    vertices all follow the head; and the ``surround_triangles`` / ``surround_points`` keywords of
    :func:`write_usd_scene` (the other triangles, every vertex after the weighted motion).
    """
    from stages.render3d.head import apply_head

    T = len(vertices)
    full = np.concatenate([vertices, np.broadcast_to(mesh["surround"], (T,) + np.shape(mesh["surround"]))], 1)
    uv = np.concatenate(
        [np.asarray(mesh["uv"], np.float64), np.broadcast_to(mesh["surround_uv"], (T,) + np.shape(mesh["surround_uv"]))], 1
    )
    triangles, weight = np.asarray(mesh["head_triangles"]), np.asarray(mesh["weight"], np.float64)
    rigid = (weight[triangles] == 1.0).all(1)
    moved = full if head is None else apply_head(full, np.asarray(head["R"], np.float64), np.asarray(head["t"], np.float64))
    baked = weight[None, :, None] * moved + (1.0 - weight[None, :, None]) * full
    return full, uv, triangles[rigid], {"surround_triangles": triangles[~rigid], "surround_points": baked}


class WriteUsd(SequenceStage):
    """``write.usd``: ``scene.usda`` (animated mesh, head xform, texture sequence, camera), textures, head pose CSV."""

    name = "write.usd"
    version = "3"
    doc = "USD scene of the 3D expression: time-sampled mesh points and UVs, head xform, texture sequence; head_pose.csv"
    inputs = {"mesh": MESH3D, "head": HEAD3D, "texture": "frames", "mask": "frames"}
    optional_inputs = frozenset({"head", "mask"})
    outputs = {"usd": "files"}
    params = (
        GEOMETRY,
        Param("fps", float, 30.0, "frame rate when the mesh bundle carries none", min=1e-3, max=1000.0),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        import cv2

        mesh, head, stream = inputs["mesh"], inputs.get("head"), inputs["texture"]
        vertices = mesh_vertices(mesh, params["geometry"], stage=self.name)
        for field in ("triangles", "uv", "camera", "size"):
            if field not in mesh:
                raise StageError(f"{self.name}: input 'mesh' has no field '{field}'")
        T = len(vertices)
        if stream.info.frames != T or (head is not None and len(head["R"]) != T):
            raise StageError(f"{self.name}: inputs 'texture'/'head' do not have the mesh's {T} frames")
        fps = float(mesh["fps"]) if "fps" in mesh else float(params["fps"])
        folder = ctx.files_dir("usd")
        (folder / "textures").mkdir(parents=True, exist_ok=True)
        names = []
        for start, chunk in stream.chunks():
            masks = inputs["mask"].read(start, start + len(chunk)) if inputs.get("mask") is not None else None
            for i, image in enumerate(chunk):
                rgba = np.concatenate([image, np.ones_like(image[..., :1]) if masks is None else masks[i]], axis=2)
                name = TEXTURE_NAME.format(start + i)
                if not cv2.imwrite(str(folder / name), cv2.cvtColor(to_uint8(np.asarray(rgba)), cv2.COLOR_RGBA2BGRA)):
                    raise StageError(f"{self.name}: cannot write {folder / name}")
                names.append(name)
            ctx.progress(len(chunk))
        triangles, uv, surround = np.asarray(mesh["triangles"]), np.asarray(mesh["uv"], np.float64), {}
        if "head_triangles" in mesh:
            vertices, uv, triangles, surround = whole_head_parts(mesh, vertices, head)
        write_usd_scene(
            folder / "scene.usda",
            vertices=vertices,
            triangles=triangles,
            uv=uv,
            size=tuple(int(v) for v in mesh["size"]),
            camera=np.asarray(mesh["camera"], np.float64),
            fps=fps,
            head_R=None if head is None else np.asarray(head["R"]),
            head_t=None if head is None else np.asarray(head["t"]),
            texture_files=names,
            **surround,
        )
        if head is not None:
            write_pose_csv(folder / "head_pose.csv", head, fps=fps)
        return {"usd": None}
