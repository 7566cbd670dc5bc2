"""Test stages, a throw-away plugin distribution that registers them, and a CLI launcher.

The stages are registered through the entry-point group exactly as a third-party package would
(a ``*.dist-info`` folder with ``entry_points.txt`` on ``PYTHONPATH``), together with the
built-in video stages.

Environment knobs (read by the stages, never part of their cache keys) slow them down so that
a test can kill a run at a chosen moment: ``RUNNER_TEST_SLEEP`` seconds per chunk of
``test.add``, ``RUNNER_TEST_WRITE_SLEEP`` seconds per chunk written by ``test.slow_write``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from runner.bundle import BundleType, Field
from runner.stage import Context, FrameStage, Param, SequenceStage, StreamInfo
from stages.video import WriteVideo

REPO = Path(__file__).resolve().parents[2]
DATA = Path(__file__).resolve().parent / "data"
TINY = REPO / "fixtures" / "clips" / "tiny.mp4"

ENTRY_POINTS = {
    "video.decode": "stages.video:VideoDecode",
    "image.gray": "stages.video:ImageGray",
    "write.video": "stages.video:WriteVideo",
    "test.add": "tests.runner.helpers:AddFrames",
    "test.mean": "tests.runner.helpers:MeanSeries",
    "test.warn_mean": "tests.runner.helpers:WarningMeanSeries",
    "test.typed_mean": "tests.runner.helpers:TypedMeanSeries",
    "test.table": "tests.runner.helpers:SeriesTable",
    "test.slow_write": "tests.runner.helpers:SlowWriteVideo",
    "test.every_other": "tests.runner.helpers:EveryOtherFrame",
    "test.half_size": "tests.runner.helpers:HalfSize",
    "test.half_size_on_demand": "tests.runner.helpers:HalfSizeOnDemand",
    "test.plot": "tests.runner.helpers:Plot",
}


class AddFrames(FrameStage):
    """frames + value from frame ``start_at`` on (saturating); ``note`` changes the cache key but
    not the output. Reads one frame of context each side (window 1) to exercise clamped reads."""

    name = "test.add"
    version = "1"
    inputs = {"frames": "frames"}
    outputs = {"frames": "frames"}
    window = 1
    params = (
        Param("value", int, 0, "added to every pixel"),
        Param("note", str, "", "ignored"),
        Param("start_at", int, 0, "first frame the value is added to"),
    )

    def process(
        self, start: int, stop: int, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context
    ) -> dict[str, Any]:
        frames = inputs["frames"].read(start - self.window, stop + self.window)[self.window : -self.window]
        time.sleep(float(os.environ.get("RUNNER_TEST_SLEEP", "0")))
        added = np.arange(start, stop)[:, None, None, None] >= params["start_at"]
        frames = frames.astype(np.int16) + params["value"] * added
        return {"frames": np.clip(frames, 0, 255).astype(np.uint8)}


class HalfSize(FrameStage):
    """Every other pixel of each row and column: a stage giving its frames another size (as
    ``render3d``, ``preview.side_by_side``), frame t from input frame t."""

    name = "test.half_size"
    version = "1"
    inputs = {"frames": "frames"}
    outputs = {"frames": "frames"}

    def stream_info(self, inputs: Mapping[str, Any], params: Mapping[str, Any]) -> StreamInfo:
        info = inputs["frames"].info
        return StreamInfo(frames=info.frames, fps=info.fps, width=(info.width + 1) // 2, height=(info.height + 1) // 2)

    def process(
        self, start: int, stop: int, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context
    ) -> dict[str, Any]:
        return {"frames": np.ascontiguousarray(inputs["frames"].read(start, stop)[:, ::2, ::2])}


class HalfSizeOnDemand(HalfSize):
    """:class:`HalfSize` uncached (computed as read, as ``preview.side_by_side``)."""

    name = "test.half_size_on_demand"
    cached = False


class EveryOtherFrame(FrameStage):
    """A stage that would re-time its input (half the frames): the runner refuses it."""

    name = "test.every_other"
    version = "1"
    inputs = {"frames": "frames"}
    outputs = {"frames": "frames"}

    def stream_info(self, inputs: Mapping[str, Any], params: Mapping[str, Any]) -> StreamInfo:
        info = inputs["frames"].info
        return StreamInfo(frames=info.frames // 2, fps=info.fps / 2, width=info.width, height=info.height)

    def process(
        self, start: int, stop: int, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context
    ) -> dict[str, Any]:
        return {"frames": inputs["frames"].read(2 * start, 2 * stop)[::2]}


class MeanSeries(SequenceStage):
    """Mean intensity per frame: bundle ``{"mean": (T,) f8}``."""

    name = "test.mean"
    version = "1"
    inputs = {"frames": "frames"}
    outputs = {"series": "series"}

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        means = [chunk.reshape(len(chunk), -1).mean(axis=1) for _, chunk in inputs["frames"].chunks()]
        return {"series": {"mean": np.concatenate(means)}}


SERIES = BundleType(
    "series",
    "mean intensity per frame",
    (Field("mean", "f", ("T",), "", "mean intensity"), Field("frame", "iu", ("T",), "", "frame index")),
)


class TypedMeanSeries(MeanSeries):
    """``test.mean`` with a declared output type (:data:`SERIES`); ``drop`` names a field it leaves
    out of the bundle (a stage that returns less than it declares)."""

    name = "test.typed_mean"
    outputs = {"series": SERIES}
    params = (Param("drop", str, "", "a field left out of the bundle"),)

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        mean = super().run(inputs, params, ctx)["series"]["mean"]
        series = {"mean": mean, "frame": np.arange(len(mean))}
        series.pop(params["drop"], None)
        return {"series": series}


class WarningMeanSeries(MeanSeries):
    """``test.mean`` that also warns: one line of its own through ``ctx.log`` (as a stage
    warns of a poor reference frame), and a numpy ``RuntimeWarning`` (a float32 overflow)."""

    name = "test.warn_mean"

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        ctx.log.warning("warning: test.warn_mean: the series is made of test frames")
        np.float32(3e38) * np.float32(10)
        return super().run(inputs, params, ctx)


class SeriesTable(SequenceStage):
    """Writes a series bundle as ``series.json`` (a ``files`` output)."""

    name = "test.table"
    version = "1"
    inputs = {"series": "series"}
    outputs = {"table": "files"}
    params = (Param("digits", int, 3, "decimals kept"),)

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        values = [round(float(v), params["digits"]) for v in inputs["series"]["mean"]]
        (ctx.files_dir("table") / "series.json").write_text(json.dumps(values))
        return {"table": None}


class Plot(SequenceStage):
    """Draws a titled plot with matplotlib as ``plot.png`` (a ``files`` output): matplotlib
    builds its font cache the first time it lays out text."""

    name = "test.plot"
    version = "1"
    outputs = {"plot": "files"}

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        figure = Figure(figsize=(2, 1))
        FigureCanvasAgg(figure)
        figure.add_subplot().set_title("plot")
        figure.savefig(ctx.files_dir("plot") / "plot.png")
        return {"plot": None}


class SlowWriteVideo(WriteVideo):
    """``write.video`` that pauses ``RUNNER_TEST_WRITE_SLEEP`` s after each chunk it encodes."""

    name = "test.slow_write"

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        pause = float(os.environ.get("RUNNER_TEST_WRITE_SLEEP", "0"))
        return super().run(inputs, params, Context(ctx.device, ctx.files_dir, progress=lambda n: time.sleep(pause)))


def make_plugin_site(folder: Path) -> Path:
    """A folder holding ``runner_test_plugins-0.dist-info`` that registers :data:`ENTRY_POINTS`."""
    info = folder / "runner_test_plugins-0.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: runner-test-plugins\nVersion: 0\n")
    lines = ["[expression_mapping.stages]"] + [f"{name} = {target}" for name, target in ENTRY_POINTS.items()]
    (info / "entry_points.txt").write_text("\n".join(lines) + "\n")
    return folder


def cli_env(site: Path, cache: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("RUNNER_")}
    env.update(PYTHONPATH=os.pathsep.join([str(site), str(REPO)]), RUNNER_CACHE_DIR=str(cache), **extra)
    return env


def runner_cmd(*args: str | Path) -> list[str]:
    return [sys.executable, "-m", "runner.cli", *map(str, args)]


def run_cli(*args: str | Path, env: dict[str, str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(runner_cmd(*args), env=env, cwd=cwd, capture_output=True, text=True, timeout=120)


def read_log(path: Path) -> list[dict[str, Any]]:
    """Events of a ``--log-json`` file (a last line cut by a kill is dropped)."""
    events = []
    for line in path.read_text().splitlines():
        try:
            events.append(json.loads(line))
        except ValueError:
            pass
    return events


def chunk_status(events: list[dict[str, Any]], stage: str) -> dict[tuple[int, int], str]:
    return {(e["start"], e["stop"]): e["status"] for e in events if e.get("event") == "chunk" and e["stage"] == stage}


def stage_status(events: list[dict[str, Any]]) -> dict[str, str]:
    return {e["stage"]: e["status"] for e in events if e.get("event") == "stage"}


def tree_bytes(folder: Path) -> dict[str, bytes]:
    """Relative path -> bytes of every file under ``folder``."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}
