"""pipeline_3d.yaml through the CLI on the default fixture clip: the 3D render of the whole head (EXR
with the head, the plate, the mattes and Z in mm) and the USD scene come out for every frame, as
docs/render3d.md describes them."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import av
import numpy as np
import OpenImageIO as oiio
import pytest

from runner.config import load_pipeline
from runner.registry import Registry

pytestmark = [pytest.mark.slow, pytest.mark.subprocess]

REPO = Path(__file__).resolve().parent.parent
RUNNER = [sys.executable, "-c", "from runner.cli import main; main()"]


def run_cli(*args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([*RUNNER, *args], cwd=REPO, env=env, capture_output=True, text=True, timeout=900)


@pytest.fixture(scope="module")
def out(tmp_path_factory) -> Path:
    work = tmp_path_factory.mktemp("pipeline3d")
    for stage in ("render3d", "usd"):  # the 3D outputs and what they depend on; one cache
        result = run_cli(
            "run", "pipeline_3d.yaml", "--until", stage, "--out", str(work / "out"), "--cache-dir", str(work / "cache")
        )
        assert result.returncode == 0, result.stderr
    return work / "out"


def clip_frames() -> int:
    with av.open(str(REPO / "fixtures" / "clips" / "calm.mp4")) as container:
        return sum(1 for _ in container.decode(video=0))


def test_exr_frames_with_depth_in_mm(out):
    files = sorted((out / "render3d").glob("frame.*.exr"))
    assert len(files) == clip_frames()
    image = oiio.ImageInput.open(str(files[len(files) // 2]))
    spec = image.spec()
    pixels = image.read_image("float")
    image.close()
    names = spec.channelnames
    assert names[:4] == ("R", "G", "B", "A") and spec.getattribute("exmap:depth_unit") == "mm"
    assert set(names[4:]) == {"Z", "plate.R", "plate.G", "plate.B", "face.A", "filled.A"}
    get = {n: pixels[..., names.index(n)] for n in names}
    face = get["face.A"] > 0.99
    assert face.mean() > 0.1 and (get["A"][face] > 0.99).all()  # the face is inside the head
    assert np.all(np.isfinite(get["Z"]))  # the whole head covers the frame: hair, neck, background
    assert 150.0 < np.median(get["Z"][face]) < 600.0  # the pack camera's face, ~320 mm away
    assert (get["plate.G"] > 0).mean() > 0.99 and get["filled.A"].max() <= 1.0


def test_usd_scene_and_head_pose(out):
    from pxr import Usd, UsdGeom

    T = clip_frames()
    stage = Usd.Stage.Open(str(out / "usd" / "scene.usda"))
    points = UsdGeom.Mesh(stage.GetPrimAtPath("/Root/Head/Face")).GetPointsAttr()
    assert len(points.GetTimeSamples()) == T and len(points.Get(0)) > 134  # the 134 layout points and the surround
    assert len(UsdGeom.Mesh(stage.GetPrimAtPath("/Root/Surround")).GetPointsAttr().GetTimeSamples()) == T
    assert len(UsdGeom.Xformable(stage.GetPrimAtPath("/Root/Head")).GetOrderedXformOps()[0].GetAttr().GetTimeSamples()) == T
    assert len(list((out / "usd" / "textures").glob("texture.*.png"))) == T
    with (out / "usd" / "head_pose.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == T and {"yaw_deg", "tx_mm", "R22"} <= set(rows[0])


def test_pipeline_3d_is_pipeline_yaml_plus_the_3d_stages():
    registry = Registry.from_entry_points()
    base = load_pipeline(REPO / "pipeline.yaml", registry)
    three = load_pipeline(REPO / "pipeline_3d.yaml", registry)
    assert {n: (i.type, i.default) for n, i in three.inputs.items()} == {n: (i.type, i.default) for n, i in base.inputs.items()}
    for name, stage in base.stages.items():
        got = three.stages[name]
        wiring = {port: str(ref) for port, ref in got.inputs.items()}
        assert (got.uses, got.params, wiring) == (stage.uses, stage.params, {p: str(r) for p, r in stage.inputs.items()}), name
    assert set(three.stages) - set(base.stages) == {"texture", "mesh3d", "render3d", "video3d", "usd"}


def test_more_chunks_than_kept_ahead_stream_through(tmp_path):
    """`render3d` gives its frames another size than `texture`'s: its chunks read `texture`'s
    chunk by chunk, so a clip of more chunks than are computed ahead of the slowest reader (here
    12 chunks of 4 frames, `texture` read by `render3d` and `usd` at once) streams through; it
    waited forever when each `render3d` chunk's key read the whole `texture` stream."""
    (tmp_path / "pipeline.yaml").write_text(f"extends: {REPO / 'pipeline_3d.yaml'}\nchunk_frames: 4\n")
    result = run_cli(
        "run",
        str(tmp_path / "pipeline.yaml"),
        "--until",
        "video3d",
        "--until",
        "usd",
        "--out",
        str(tmp_path / "out"),
        "--cache-dir",
        str(tmp_path / "cache"),
    )
    assert result.returncode == 0, result.stderr
    assert len(list((tmp_path / "out" / "render3d").glob("frame.*.exr"))) == clip_frames() > 4 * 5
    assert (tmp_path / "out" / "video3d" / "result3d.mp4").stat().st_size > 0
