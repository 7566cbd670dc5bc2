"""A sequence stage reading a source's frames, and the sequence stages after it that read nothing
else, run in a child process beside the run (runner.offload): same published outputs as computed
in the run itself, the run reports them with the child's seconds and logs the child's events, a
second run is all cached, and a child that fails leaves the stages to the run."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from runner import offload, schedule
from runner.cache import CacheStore
from runner.config import bind_inputs, load_pipeline
from runner.execute import Options, Runner
from runner.registry import Registry
from runner.schedule import StreamingSchedule
from tests.runner.helpers import TINY, read_log, run_cli, stage_status

pytestmark = [pytest.mark.subprocess]

PIPELINE = """\
    chunk_frames: 8
    inputs:
      clip: {type: video}
    stages:
      decode: {uses: video.decode, inputs: {video: clip}}
      mean: {uses: test.mean, inputs: {frames: decode.frames}}
      table: {uses: test.table, inputs: {series: mean.series}}
      video: {uses: write.video, params: {crf: 20}, inputs: {frames: decode.frames}}
"""


@pytest.fixture
def pipeline(tmp_path: Path) -> Path:
    path = tmp_path / "two.yaml"
    path.write_text(textwrap.dedent(PIPELINE))
    return path


@pytest.mark.parametrize("way", ["fork", "interpreter"])
def test_stage_in_a_child_gives_the_same_outputs(tmp_path, pipeline, plugin_site, monkeypatch, way):
    monkeypatch.syspath_prepend(str(plugin_site))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(plugin_site), os.environ.get("PYTHONPATH")])))
    if way == "interpreter":  # as where a fork is not safe (threads running) or not possible
        monkeypatch.setattr(schedule, "offload_fork", lambda make_runner: None)
    loaded = load_pipeline(pipeline, Registry.from_entry_points())
    events: list[dict] = []
    out = tmp_path / "out"
    expected = way if offload.can_fork() else "interpreter"  # Ray, torch... loaded by another test: no fork
    Runner(loaded, {"clip": TINY}, Options(cache=CacheStore(tmp_path / "cache"), out=out, offload=True, log=events.append)).run()
    assert [e["started"] for e in events if e["event"] == "offload"] == [expected]
    moved = [stage for e in events if e["event"] == "offload" for stage in e["stages"]]
    assert moved == ["mean", "table"]  # the tracker-like stage and the table that reads only it
    reports = {e["stage"]: e for e in events if e["event"] == "stage"}
    in_child = {e["child"]["stage"]: e["child"] for e in events if e["event"] == "child" and e["child"]["event"] == "stage"}
    for stage in moved:
        assert (reports[stage]["status"], reports[stage]["reason"]) == ("ran", "in a child process beside the run")
        assert in_child[stage]["status"] == "ran"
        assert reports[stage]["seconds"] == in_child[stage]["seconds"]

    # The same pipeline computed in this process, without children, publishes the same bytes.
    Runner(loaded, {"clip": TINY}, Options(cache=CacheStore(tmp_path / "alone"), out=tmp_path / "alone_out")).run()
    for published in ("table/series.json", "video/video.mp4"):
        assert (out / published).read_bytes() == (tmp_path / "alone_out" / published).read_bytes()


def test_the_command_runs_a_child_then_finds_everything_cached(env, tmp_path, pipeline, plugin_site, monkeypatch):
    out = tmp_path / "out"
    first = run_cli("run", pipeline, "--in", TINY, "--out", out, "--log-json", tmp_path / "1.jsonl", env=env, cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    offloads = [e for e in read_log(tmp_path / "1.jsonl") if e["event"] == "offload"]
    assert [(e["stages"], e["started"]) for e in offloads] == [(["mean", "table"], "fork")]  # a fresh process
    assert first.stderr == ""
    monkeypatch.syspath_prepend(str(plugin_site))
    Runner(
        load_pipeline(pipeline, Registry.from_entry_points()),
        {"clip": TINY},
        Options(cache=CacheStore(tmp_path / "alone"), out=tmp_path / "alone_out"),
    ).run()
    for published in ("table/series.json", "video/video.mp4"):
        assert (out / published).read_bytes() == (tmp_path / "alone_out" / published).read_bytes()
    second = run_cli("run", pipeline, "--in", TINY, "--out", out, "--log-json", tmp_path / "2.jsonl", env=env, cwd=tmp_path)
    assert second.returncode == 0, second.stderr
    assert not [e for e in read_log(tmp_path / "2.jsonl") if e["event"] == "offload"]  # cached: no child
    assert set(stage_status(read_log(tmp_path / "2.jsonl")).values()) <= {"cached", "on demand"}


def test_a_failed_child_leaves_the_stage_to_the_run(tmp_path, pipeline, plugin_site, monkeypatch):
    monkeypatch.syspath_prepend(str(plugin_site))
    started = []

    def failing(argument: str) -> subprocess.Popen:
        started.extend(json.loads(argument)["until"])
        return subprocess.Popen([sys.executable, "-c", "raise SystemExit(1)"], stdout=subprocess.PIPE, text=True)

    monkeypatch.setattr(schedule, "offload_start", failing)
    monkeypatch.setattr(schedule, "offload_fork", lambda make_runner: None)  # the new-interpreter way
    events = []
    options = Options(cache=CacheStore(tmp_path / "cache"), out=tmp_path / "out", offload=True, log=events.append)
    reports = {r.stage: r for r in Runner(load_pipeline(pipeline, Registry.from_entry_points()), {"clip": TINY}, options).run()}
    assert started and len(started) == len(set(started))  # each offered to a child once
    for stage in started:
        assert (reports[stage].status, reports[stage].reason) == ("ran", "")  # computed here after all
    assert json.loads((tmp_path / "out" / "table" / "series.json").read_text())


def test_the_child_takes_the_performers_branch(tmp_path):
    """In the paper's pipeline, once the clip is set up, the child takes the performer's pack the
    tracker waits for, the tracker, and the sequence stages after it that read nothing of the
    target's (not `map`, which reads the target's pack; not the frame stages); nothing while the
    performer's pack is found in the cache (a cached run must not start a child)."""
    repo = Path(__file__).resolve().parents[2]
    loaded = load_pipeline(repo / "pipeline_paper.yaml", Registry.from_entry_points())
    bound = bind_inputs(loaded, clip=None, named=[])
    runner = Runner(loaded, bound, Options(cache=CacheStore(tmp_path / "cache"), offload=True))
    waiting = [node for name, node in loaded.stages.items() if name != "decode"]

    def offloaded(stage: str, done: set[str]) -> list[str]:
        scheduled = StreamingSchedule(runner, emit=lambda report: None)
        scheduled.waiting, scheduled.done = list(waiting), done
        return scheduled._offload_stages(loaded.stages[stage])

    stages = offloaded("track", {"decode"})
    assert stages == ["performer_pack", "track", "smooth", "compensate", "pose", "compensate3d"]
    assert offloaded("track", set()) == []  # the clip is not set up yet
    assert offloaded("build", {"decode"}) == []  # reads no clip
    # a cached run: the performer's pack is stored, so the run visits it first and looks the tracker up
    Runner(loaded, bound, Options(cache=CacheStore(tmp_path / "cache"), until=("performer_pack",))).run()
    assert offloaded("track", {"decode"}) == []
