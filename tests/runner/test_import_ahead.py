"""A stage's declared ``imports`` are imported by the scheduling thread while it waits for a
stream, before the stage runs (runner.schedule.StreamingSchedule.import_ahead)."""

from __future__ import annotations

import sys
import textwrap
import threading
from pathlib import Path

from runner.cache import CacheStore
from runner.config import load_pipeline
from runner.execute import Options, Runner
from runner.registry import Registry
from runner.schedule import StreamingSchedule
from runner.stage import SequenceStage
from tests.runner.test_streaming import N, Double, Reader, Source

MODULE = "tests.runner.imported_ahead"
SEEN: dict[str, object] = {}
IMPORTED = threading.Event()


class HeldSource(Source):
    """The ramp clip, its last chunk held until the imports ahead were made (at most 60 s): the
    stream is still computing while the run waits for it, whatever the machine's speed."""

    def process(self, start, stop, inputs, params, ctx):
        if stop == N:
            IMPORTED.wait(60.0)
        return super().process(start, stop, inputs, params, ctx)


class After(SequenceStage):
    """Runs after the readers; records whether its declared module was imported before it ran."""

    name, version = "s.after", "1"
    inputs = {"all": "all"}
    outputs = {"done": "done"}
    imports = (MODULE, "no_such_module_for_the_test")

    def run(self, inputs, params, ctx):
        SEEN["imported_before_run"] = MODULE in sys.modules
        return {"done": {"ok": inputs["all"]["frames"][:1]}}


def test_declared_modules_are_imported_while_the_stream_runs(tmp_path: Path, monkeypatch):
    monkeypatch.delitem(sys.modules, MODULE, raising=False)
    pipeline = tmp_path / "p.yaml"
    pipeline.write_text(
        textwrap.dedent("""
        chunk_frames: 4
        stages:
          source: {uses: s.source}
          double: {uses: s.double, inputs: {frames: source.frames}}
          first: {uses: s.reader, inputs: {frames: double.frames}}
          after: {uses: s.after, inputs: {all: first.all}}
    """)
    )
    registry = Registry(classes=[HeldSource, Double, Reader, After])
    IMPORTED.clear()
    importer = []
    original = StreamingSchedule.import_ahead

    def spy(self):
        importer.append(threading.current_thread())
        original(self)
        if MODULE in sys.modules:
            IMPORTED.set()

    monkeypatch.setattr(StreamingSchedule, "import_ahead", spy)
    reports = Runner(load_pipeline(pipeline, registry), {}, Options(cache=CacheStore(tmp_path / "cache"))).run()
    assert {r.stage: r.status for r in reports}["after"] == "ran"  # a module that cannot import is left alone
    assert SEEN["imported_before_run"] and importer and importer[0] is threading.main_thread()
