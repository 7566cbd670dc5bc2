"""mesh3d.synthesize -> render3d.head -> render3d and write.usd on the fixture pack, called directly."""

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from runner.stage import StageError
from stages.mesh3d.stage import Mesh3DSynthesize
from stages.render3d.stage import HeadPose3D, Render3D
from stages.writers.usd import WriteUsd
from runner.lifecycle import opened
from tests.memory_stream import MemoryStream, files_context, process_once

PACK = Path("fixtures/packs/target")


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    from stages.actor_pack import load_pack
    from stages.pack.bundles import pack_to_bundles

    root = tmp_path_factory.mktemp("render3d")
    ctx = files_context(root)
    pack = load_pack(PACK)
    xy = np.stack([pack.neutral.points, pack.standard.points])
    bundles = pack_to_bundles(pack)
    pack_inputs = {port: bundles[port] for port in ("layout", "images", "model3d", "camera")}
    mesh = Mesh3DSynthesize().run({**pack_inputs, "points": {"xy": xy, "fps": np.array(25.0)}}, {}, ctx)["mesh"]
    R = np.stack([np.eye(3), Rotation.from_euler("y", 20, degrees=True).as_matrix()])
    pose = {"R": R, "tvec": np.zeros((2, 3)), "scale": np.ones(2), "valid": np.ones(2, bool)}
    target = {port: bundles[port] for port in ("geometry", "model3d", "camera")}
    head = HeadPose3D().run({**target, "pose": pose}, {"translation_scale": 1.0}, ctx)["head"]
    images = np.stack([pack.neutral.image, pack.standard.image]).astype(np.float32) / 255.0
    texture = MemoryStream(images.astype(np.float16), fps=25.0, chunk=1)
    inputs = {"texture": texture, "mesh": mesh, "head": head}
    params = {"samples": 4, "resolution_scale": 1.0, "geometry": "synthesized", "compression": "zip"}
    out = process_once(Render3D(), 0, 2, inputs, params, ctx)
    return root, pack, mesh, head, texture, out, target


def test_mesh_bundle_shapes(chain):
    _, pack, mesh, head, _, _, _ = chain
    N = pack.layout.n_points
    assert mesh["vertices"].shape == (2, N, 3) and mesh["uv"].shape == (2, N, 2)
    assert mesh["coeffs"].shape[0] == 2 and np.allclose(mesh["coeffs"].sum(-1), 1.0)
    np.testing.assert_allclose(head["t"][0], 0.0, atol=1e-9)


def test_render_outputs_and_exr_depth_in_mm(chain):
    import OpenImageIO as oiio

    root, pack, mesh, _, _, out, _ = chain
    W, H = pack.image_size
    assert out["frames"].shape == (2, H, W, 3) and out["mask"].shape == (2, H, W, 1) and out["depth"].shape == (2, H, W, 1)
    exr = oiio.ImageInput.open(str(root / "exr" / "frame.000000.exr"))
    spec = exr.spec()
    assert spec.channelnames == ("R", "G", "B", "A", "Z")
    assert spec.getattribute("exmap:depth_unit") == "mm"
    pixels = exr.read_image("float")
    exr.close()
    np.testing.assert_array_equal(pixels[..., 4], out["depth"][0, ..., 0])
    # at the reference pose, the depth under a mesh vertex is that vertex's camera z in mm
    k = pack.layout.index("nose_bridge_1")
    u, v = np.round(pack.neutral.points[k]).astype(int)
    assert pixels[v, u, 4] == pytest.approx(mesh["vertices"][0, k, 2], abs=1.5)
    assert 200.0 < pixels[v, u, 4] < 500.0  # the pack camera sees the face about 320 mm away
    # the turned frame moves the face, frame 0 reproduces the texture inside the mesh
    inside = out["mask"][0, ..., 0] > 0.999
    err = np.abs(out["frames"][0].astype(np.float32) - pack.neutral.image / 255.0)[inside].mean()
    assert err < 0.02
    assert np.abs(out["mask"][1].astype(np.float32) - out["mask"][0]).mean() > 0.01


def test_write_usd_stage(chain):
    from pxr import Usd, UsdGeom

    root, pack, mesh, head, texture, _, _ = chain
    ctx = files_context(root)
    WriteUsd().run({"mesh": mesh, "head": head, "texture": texture}, {"geometry": "synthesized", "fps": 30.0}, ctx)
    stage = Usd.Stage.Open(str(root / "usd" / "scene.usda"))
    points = UsdGeom.Mesh(stage.GetPrimAtPath("/Root/Head/Face")).GetPointsAttr()
    assert points.GetTimeSamples() == [0.0, 1.0]
    assert len(points.Get(1)) == pack.layout.n_points
    assert stage.GetTimeCodesPerSecond() == 25.0
    assert (root / "usd" / "textures" / "texture.000001.png").is_file()
    assert (root / "usd" / "head_pose.csv").read_text().count("\n") == 3


def test_head_carries_the_mesh_models_depth_and_pivot(chain):
    _, _, mesh, head, _, _, _ = chain
    np.testing.assert_allclose(head["pivot"], mesh["pivot"], atol=1e-9)
    np.testing.assert_allclose(head["depth"], mesh["neutral"][:, 2], atol=1e-9)
    np.testing.assert_allclose(head["camera"], mesh["camera"])


def test_resolution_scale_renders_the_same_picture_larger(chain, tmp_path):
    import cv2

    _, pack, mesh, head, texture, out, _ = chain
    params = {"samples": 4, "resolution_scale": 2.0, "geometry": "synthesized", "compression": "zip"}
    big = process_once(Render3D(), 0, 1, {"texture": texture, "mesh": mesh, "head": head}, params, files_context(tmp_path))
    W, H = pack.image_size
    assert big["frames"].shape == (1, 2 * H, 2 * W, 3)
    small = cv2.resize(big["mask"][0].astype(np.float32), (W, H), interpolation=cv2.INTER_AREA)
    assert np.abs(small - out["mask"][0, ..., 0].astype(np.float32)).mean() < 0.01


def test_missing_egl_is_a_stage_error_naming_the_packages(chain, tmp_path, monkeypatch):
    import stages.render3d.raster as raster

    _, _, mesh, head, texture, _, _ = chain

    def no_egl():
        raise RuntimeError(
            "no headless OpenGL context (EGL): test; install libegl1 libegl-mesa0 libgl1-mesa-dri (.ci/install-egl)"
        )

    monkeypatch.setattr(raster, "gl_context", no_egl)
    params = {"samples": 4, "resolution_scale": 1.5, "geometry": "synthesized", "compression": "zip"}
    with pytest.raises(StageError, match="install-egl"):
        process_once(Render3D(), 0, 1, {"texture": texture, "mesh": mesh, "head": head}, params, files_context(tmp_path))


def test_chunks_rendered_on_two_threads_at_once_equal_one_thread(chain, tmp_path):
    """The runner computes a stage's chunks on several producer threads, one at a time for this
    "single" stage (runner.lifecycle): the two frames rendered from two threads at once (one
    stage instance, its one GL context) equal those rendered on one."""
    import threading

    root, _, mesh, head, texture, out, _ = chain
    params = {"samples": 4, "resolution_scale": 1.0, "geometry": "synthesized", "compression": "zip"}
    inputs = {"texture": texture, "mesh": mesh, "head": head}
    stage, results, errors = Render3D(), {}, []
    assert stage.threading == "single"
    start = threading.Barrier(2)

    def render(frame: int) -> None:
        try:
            start.wait(10)
            for _ in range(3):
                ctx = files_context(tmp_path / str(frame))
                results[frame] = life.call(inputs, params, lambda: stage.process(frame, frame + 1, inputs, params, ctx))
        except Exception as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    with opened(stage, inputs, params) as life:
        threads = [threading.Thread(target=render, args=(frame,)) for frame in (0, 1)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    assert stage._renderer is None  # closed: its GL context released
    assert errors == []
    for frame in (0, 1):
        for port in ("frames", "mask", "depth"):
            np.testing.assert_array_equal(results[frame][port][0], out[port][frame])


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    """The whole head: mesh3d with the synthesis model, rendered at rest and turned."""
    from stages.actor_pack import load_pack
    from stages.pack.bundles import pack_to_bundles
    from stages.synthesis.build import build_synthesis_model

    root = tmp_path_factory.mktemp("whole")
    ctx = files_context(root)
    pack = load_pack(PACK)
    bundles = pack_to_bundles(pack)
    model = build_synthesis_model(pack)
    xy = np.stack([pack.neutral.points, pack.neutral.points])
    inputs = {port: bundles[port] for port in ("layout", "images", "model3d", "camera")}
    mesh = Mesh3DSynthesize().run({**inputs, "points": {"xy": xy, "fps": np.array(25.0)}, "model": model}, {}, ctx)["mesh"]
    R = np.stack([np.eye(3), Rotation.from_euler("y", 20, degrees=True).as_matrix()])
    pose = {"R": R, "tvec": np.zeros((2, 3)), "scale": np.ones(2), "valid": np.ones(2, bool)}
    target = {port: bundles[port] for port in ("geometry", "model3d", "camera")}
    head = HeadPose3D().run({**target, "pose": pose}, {"translation_scale": 1.0}, ctx)["head"]
    image = pack.neutral.image.astype(np.float32) / 255.0
    texture = MemoryStream(np.stack([image, image]).astype(np.float16), fps=25.0, chunk=1)
    params = {"samples": 4, "resolution_scale": 1.0, "geometry": "lifted", "compression": "zip"}
    out = process_once(Render3D(), 0, 2, {"texture": texture, "mesh": mesh, "head": head}, params, ctx)
    return root, pack, mesh, head, texture, out


def test_whole_head_at_rest_reproduces_its_texture_over_the_whole_frame(whole):
    _, pack, mesh, _, _, out = whole
    N = pack.layout.n_points
    assert mesh["surround"].shape[0] == mesh["surround_uv"].shape[0] and mesh["weight"].shape == (N + len(mesh["surround"]),)
    rest = out["frames"][0].astype(np.float32)
    err = np.abs(rest - pack.neutral.image / 255.0)
    assert np.median(err) < 0.01 and err.mean() < 0.02  # hair, neck, background included: no face mask on black
    assert out["filled"][0].max() < 0.05  # every pixel covered by the mesh and real
    turned = out["frames"][1].astype(np.float32)
    corners = np.zeros(turned.shape[:2], bool)
    corners[:8, :8] = corners[:8, -8:] = True
    assert np.abs(turned - rest).mean() > 0.01  # the head turned
    assert np.abs(turned - rest)[corners].mean() < 0.02  # the background stayed


def test_whole_head_usd_validates_with_a_rigid_head_and_a_deforming_surround(whole):
    from pxr import Usd, UsdGeom, UsdValidation

    root, pack, mesh, head, texture, _ = whole
    ctx = files_context(root)
    WriteUsd().run({"mesh": mesh, "head": head, "texture": texture}, {"geometry": "lifted", "fps": 25.0}, ctx)
    path = root / "usd" / "scene.usda"
    stage = Usd.Stage.Open(str(path))
    errors = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators()).Validate(stage)
    assert [e.GetMessage() for e in errors] == []
    face = UsdGeom.Mesh(stage.GetPrimAtPath("/Root/Head/Face"))
    surround = UsdGeom.Mesh(stage.GetPrimAtPath("/Root/Surround"))
    V = pack.layout.n_points + len(mesh["surround"])
    assert len(face.GetPointsAttr().Get(0)) == len(surround.GetPointsAttr().Get(1)) == V
    n_face = len(face.GetFaceVertexCountsAttr().Get())
    n_surround = len(surround.GetFaceVertexCountsAttr().Get())
    assert n_face + n_surround == len(mesh["head_triangles"]) and n_face > 0 and n_surround > 0
    # a static vertex (weight 0) stays put in the turned frame; the head's own vertices move with its xform
    static = int(np.flatnonzero(mesh["weight"] == 0)[0])
    np.testing.assert_allclose(surround.GetPointsAttr().Get(1)[static], surround.GetPointsAttr().Get(0)[static], atol=1e-3)
