"""A stage's lifecycle in a run (runner.lifecycle): open before the first call, close once after
the last (also on a failure), neither for a stage served from the cache, and the calls of a
``"single"`` stage one at a time while a reentrant stage's overlap."""

from __future__ import annotations

import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from runner.cache import CacheStore
from runner.config import load_pipeline
from runner.execute import Options, Runner, StageFailed
from runner.lifecycle import Lifecycle, opened
from runner.registry import Registry, RegistryError
from runner.stage import FrameStage, Param, SequenceStage, StageError, StreamInfo

N, H, W = 12, 2, 3
EVENTS: list[tuple[str, str]] = []  # (stage class name, "open" | "process" | "run" | "close"), in order
EVENTS_LOCK = threading.Lock()


def event(stage: object, what: str) -> None:
    with EVENTS_LOCK:
        EVENTS.append((type(stage).__name__, what))


class Source(FrameStage):
    name, version = "t.source", "1"
    outputs = {"frames": "frames"}
    params = (Param("fail_at", int, -1, "raise StageError on the chunk holding this frame"),)

    def stream_info(self, inputs, params):
        return StreamInfo(N, 25.0, W, H)

    def open(self, inputs, params, ctx):
        assert ctx.device == "cpu"
        event(self, "open")
        self.opened = True

    def process(self, start, stop, inputs, params, ctx):
        assert self.opened
        event(self, "process")
        if start <= params["fail_at"] < stop:
            raise StageError("cannot compute")
        return {"frames": np.full((stop - start, H, W, 1), 7, np.uint8)}

    def close(self, ctx):
        event(self, "close")
        self.opened = False


class Total(SequenceStage):
    name, version = "t.total", "1"
    inputs = {"frames": "frames"}
    outputs = {"total": "total"}

    def open(self, inputs, params, ctx):
        event(self, "open")

    def run(self, inputs, params, ctx):
        event(self, "run")
        return {"total": {"sum": np.array(sum(int(chunk.sum()) for _, chunk in inputs["frames"].chunks()))}}

    def close(self, ctx):
        event(self, "close")


PIPELINE = """
chunk_frames: 4
stages:
  source: {uses: t.source}
  total: {uses: t.total, inputs: {frames: source.frames}}
"""


def run(tmp_path: Path, overrides: tuple[str, ...] = ()) -> list[tuple[str, str]]:
    EVENTS.clear()
    path = tmp_path / "p.yaml"
    path.write_text(textwrap.dedent(PIPELINE))
    pipeline = load_pipeline(path, Registry(classes=[Source, Total]), overrides=list(overrides))
    try:
        Runner(pipeline, {}, Options(cache=CacheStore(tmp_path / "cache"))).run()
    finally:
        events = list(EVENTS)
    return events


def test_each_stage_is_opened_before_its_calls_and_closed_once_after(tmp_path):
    events = run(tmp_path)
    for stage, calls in (("Source", ["process"] * 3), ("Total", ["run"])):
        assert [what for name, what in events if name == stage] == ["open", *calls, "close"]


def test_a_stage_served_from_the_cache_is_neither_opened_nor_closed(tmp_path):
    run(tmp_path)
    assert run(tmp_path) == []


def test_a_failing_stage_is_closed(tmp_path):
    with pytest.raises(StageFailed, match="cannot compute"):
        run(tmp_path, overrides=("source.fail_at=5",))
    source = [what for name, what in EVENTS if name == "Source"]
    assert source[0] == "open" and source[-1] == "close" and source.count("close") == 1


class Overlap(FrameStage):
    """Counts how many of its calls run at once."""

    name, version = "t.overlap", "1"
    outputs = {"frames": "frames"}

    def __init__(self):
        self.now = self.most = 0
        self.lock = threading.Lock()

    def process(self, start, stop, inputs, params, ctx):
        with self.lock:
            self.now += 1
            self.most = max(self.most, self.now)
        time.sleep(0.02)
        with self.lock:
            self.now -= 1
        return {}


class SingleOverlap(Overlap):
    threading = "single"


@pytest.mark.parametrize(("cls", "overlap"), [(Overlap, True), (SingleOverlap, False)])
def test_single_stages_are_called_one_at_a_time_and_reentrant_ones_at_once(cls, overlap):
    stage = cls()
    life = Lifecycle(stage, device="cpu")
    barrier = threading.Barrier(4)

    def call() -> None:
        barrier.wait(10)
        life.call({}, {}, lambda: stage.process(0, 1, {}, {}, None))

    threads = [threading.Thread(target=call) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert (stage.most > 1) == overlap


def test_opened_opens_and_closes_around_calls_outside_a_run():
    stage = Source()
    with opened(stage, {}, {}):
        assert stage.process(0, 2, {}, {"fail_at": -1}, None)["frames"].shape == (2, H, W, 1)
    assert stage.opened is False


def test_an_unknown_threading_declaration_is_refused():
    class Odd(Source):
        name = "t.odd"
        threading = "parallel"

    with pytest.raises(RegistryError, match="'threading' must be one of 'reentrant', 'single'"):
        Registry(classes=[Odd])
