"""write.usd: the animated mesh re-opens with pxr with its time samples, points, UVs, texture sequence and head xform."""

import numpy as np
import pytest

from stages.writers.usd import FLIP, write_usd_scene

pxr = pytest.importorskip("pxr")


def scene(tmp_path, T=3, V=5):
    rng = np.random.default_rng(0)
    vertices = rng.normal(0, 20, (T, V, 3)) + np.array([0, 0, 300.0])
    uv = rng.uniform(0, 100, (T, V, 2))
    R = np.stack([np.eye(3)] * T)
    R[1] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    t = rng.normal(0, 5, (T, 3))
    path = tmp_path / "scene.usda"
    write_usd_scene(
        path,
        vertices=vertices,
        triangles=np.array([[0, 1, 2], [2, 3, 4]]),
        uv=uv,
        size=(100, 120),
        camera=np.array([[384.0, 0, 49.5], [0, 384.0, 59.5], [0, 0, 1]]),
        fps=25.0,
        head_R=R,
        head_t=t,
        texture_files=[f"textures/texture.{k:06d}.png" for k in range(T)],
    )
    return path, vertices, uv, R, t


def test_usd_reopens_with_time_sampled_points_uvs_textures_and_head(tmp_path):
    from pxr import Usd, UsdGeom, UsdShade

    path, vertices, uv, R, t = scene(tmp_path)
    stage = Usd.Stage.Open(str(path))
    assert stage.GetTimeCodesPerSecond() == 25.0 and stage.GetEndTimeCode() == 2
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y and UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.001)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Root/Head/Face"))
    points = mesh.GetPointsAttr()
    assert points.GetTimeSamples() == [0.0, 1.0, 2.0]
    for f in range(3):
        got = np.array(points.Get(f))
        assert got.shape == (5, 3)
        np.testing.assert_allclose(got, vertices[f] @ FLIP, atol=1e-3)
    assert list(mesh.GetFaceVertexCountsAttr().Get()) == [3, 3]
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    assert st.GetInterpolation() == UsdGeom.Tokens.vertex and st.GetAttr().GetTimeSamples() == [0.0, 1.0, 2.0]
    np.testing.assert_allclose(np.array(st.Get(1))[:, 0], (uv[1, :, 0] + 0.5) / 100, atol=1e-6)
    material, _ = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()
    assert material.GetPath() == "/Root/Materials/Face"
    file_in = UsdShade.Shader(stage.GetPrimAtPath("/Root/Materials/Face/Texture")).GetInput("file")
    assert file_in.GetAttr().GetTimeSamples() == [0.0, 1.0, 2.0]
    assert file_in.Get(2).path == "textures/texture.000002.png"
    head = UsdGeom.Xformable(stage.GetPrimAtPath("/Root/Head"))
    for f in range(3):
        M = np.array(head.ComputeLocalToWorldTransform(f))
        x = vertices[f, 0]
        moved = np.append(x @ FLIP, 1.0) @ M  # USD row vectors
        np.testing.assert_allclose(moved[:3], (R[f] @ x + t[f]) @ FLIP, atol=1e-6)
    assert stage.GetPrimAtPath("/Root/Camera").IsA(UsdGeom.Camera)


def test_front_faces_wind_counter_clockwise_towards_the_usd_camera(tmp_path):
    from pxr import Usd, UsdGeom

    # one triangle facing the camera: counter-clockwise on screen with y down (pipeline convention)
    vertices = np.array([[[-10.0, -10.0, 300.0], [10.0, -10.0, 300.0], [0.0, 10.0, 300.0]]])
    path = tmp_path / "one.usda"
    write_usd_scene(
        path,
        vertices=vertices,
        triangles=np.array([[0, 1, 2]]),
        uv=np.zeros((1, 3, 2)),
        size=(10, 10),
        camera=np.eye(3),
        fps=30.0,
    )
    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Root/Head/Face"))
    p = np.array(mesh.GetPointsAttr().Get(0))[np.array(mesh.GetFaceVertexIndicesAttr().Get())]
    normal = np.cross(p[1] - p[0], p[2] - p[0])  # right-handed orientation
    assert normal @ (-p.mean(0)) > 0  # points towards the camera at the origin (looking down -Z)


def validation_errors(path):
    """usd-core's validators (UsdValidation, every registered validator) on the layer: ``[(name, message)]``."""
    from pxr import Usd, UsdValidation

    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    errors = UsdValidation.ValidationContext(validators).Validate(Usd.Stage.Open(str(path)))
    return [(e.GetName(), e.GetMessage()) for e in errors]


def test_scene_passes_usd_core_validation_and_its_textures_resolve(tmp_path):
    import cv2
    from pxr import UsdUtils

    path, *_ = scene(tmp_path)
    (tmp_path / "textures").mkdir()
    for k in range(3):
        cv2.imwrite(str(tmp_path / f"textures/texture.{k:06d}.png"), np.zeros((12, 10, 4), np.uint8))
    assert validation_errors(path) == []
    # what an importer gathers to package the scene: the layer and its time-sampled texture files
    layers, assets, unresolved = UsdUtils.ComputeAllDependencies(str(path))
    assert [layer.realPath for layer in layers] == [str(path)]
    assert sorted(assets) == [str(tmp_path / f"textures/texture.{k:06d}.png") for k in range(3)] and not unresolved
