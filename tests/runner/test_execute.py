"""The scheduler in-process: frame stages with windows and bundle outputs, concatenation across
chunks, --jobs, and stage errors, against numpy ground truth."""

from __future__ import annotations

import textwrap
import time
from pathlib import Path

import numpy as np
import yaml
import pytest

from runner.cache import CacheStore
from runner.config import load_pipeline
from runner.execute import Options, Runner, StageFailed
from runner.plan import make_plan
from runner.registry import Registry
from runner.stage import FrameStage, Param, SequenceStage, StageError, StreamInfo

N, H, W = 23, 4, 5


def clip() -> np.ndarray:
    """Frame t is filled with t (so a frame's index can be read back from its pixels)."""
    return np.broadcast_to(np.arange(N, dtype=np.uint8)[:, None, None, None], (N, H, W, 1)).copy()


class Ramp(FrameStage):
    """Frames of :func:`clip`, and per frame a bundle row ``index``."""

    name, version = "t.ramp", "1"
    outputs = {"frames": "frames", "rows": "rows"}
    params = (Param("fail_at", int, -1, "raise StageError on the chunk holding this frame"),)

    def stream_info(self, inputs, params):
        return StreamInfo(N, 25.0, W, H)

    def process(self, start, stop, inputs, params, ctx):
        if start <= params["fail_at"] < stop:
            raise StageError(f"frame {params['fail_at']}: cannot compute")
        return {
            "frames": clip()[start:stop],
            "rows": {"index": np.arange(start, stop), "names": np.array(["f"] * (stop - start))},
        }


class Blur(FrameStage):
    """Temporal mean over ``window`` frames each side (edges replicated)."""

    name, version, window = "t.blur", "1", 2
    inputs = {"frames": "frames"}
    outputs = {"frames": "frames"}

    def process(self, start, stop, inputs, params, ctx):
        got = inputs["frames"].read(start - 2, stop + 2).astype(np.float64)
        out = np.stack([got[i : i + 5].mean(axis=0) for i in range(stop - start)])
        return {"frames": np.round(out * 10).astype(np.uint16)}


class Collect(SequenceStage):
    """Whole-clip view of a frame stream and a bundle."""

    name, version = "t.collect", "1"
    inputs = {"frames": "frames", "rows": "rows"}
    outputs = {"all": "all"}

    def run(self, inputs, params, ctx):
        frames = np.concatenate([chunk for _, chunk in inputs["frames"].chunks()])
        return {"all": {"frames": frames, "index": inputs["rows"]["index"], "names": inputs["rows"]["names"]}}


REGISTRY = Registry(classes=[Ramp, Blur, Collect])
PIPELINE = """
chunk_frames: 4
stages:
  ramp: {uses: t.ramp}
  blur: {uses: t.blur, inputs: {frames: ramp.frames}}
  collect: {uses: t.collect, inputs: {frames: blur.frames, rows: ramp.rows}}
"""


def run(tmp_path: Path, *, jobs: int = 1, overrides: tuple[str, ...] = ()) -> Runner:
    path = tmp_path / "p.yaml"
    path.write_text(textwrap.dedent(PIPELINE))
    pipeline = load_pipeline(path, REGISTRY, overrides=list(overrides))
    runner = Runner(pipeline, {}, Options(cache=CacheStore(tmp_path / "cache"), jobs=jobs))
    runner.run()
    return runner


@pytest.mark.parametrize("jobs", [1, 3])
def test_windows_and_bundles_across_chunks(tmp_path, jobs):
    runner = run(tmp_path, jobs=jobs)
    result = runner.values[("collect", "all")].get()
    padded = np.concatenate([clip()[:1]] * 2 + [clip()] + [clip()[-1:]] * 2).astype(np.float64)
    truth = np.stack([padded[t : t + 5].mean(axis=0) for t in range(N)])
    np.testing.assert_array_equal(result["frames"], np.round(truth * 10).astype(np.uint16))
    np.testing.assert_array_equal(result["index"], np.arange(N))
    assert result["names"].dtype.kind == "U" and len(runner.entries["blur"]) == 6  # ceil(23 / 4)


def test_stage_error_names_the_stage_and_keeps_finished_chunks(tmp_path):
    with pytest.raises(StageFailed, match=r"stage 'ramp' \(t.ramp\): frame 9: cannot compute"):
        run(tmp_path, overrides=("ramp.fail_at=9",))
    store = CacheStore(tmp_path / "cache")
    stored = sorted((e.record["stage"], e.record["range"]) for e in store.iter_entries() if "range" in e.record)
    # blur streams from ramp: its first chunk (reading ramp frames 0..5) finished before ramp failed;
    # ramp's producer threads (one per core) may also have finished chunks after the failing one.
    assert {("blur", (0, 4)), ("ramp", (0, 4)), ("ramp", (4, 8))} <= {(stage, tuple(r)) for stage, r in stored}
    assert ("ramp", [8, 12]) not in stored and all(r[0] < 8 for stage, r in stored if stage == "blur")
    assert not list((tmp_path / "cache" / "locks").glob("*.lock"))


def test_bad_stage_output_is_reported(tmp_path):
    class Wrong(Ramp):
        name = "t.wrong"

        def process(self, start, stop, inputs, params, ctx):
            return {"frames": clip()[start : stop + 1], "rows": {"index": np.arange(start, stop)}}

    path = tmp_path / "p.yaml"
    path.write_text("stages:\n  w: {uses: t.wrong}\n")
    pipeline = load_pipeline(path, Registry(classes=[Wrong]))
    with pytest.raises(StageFailed, match=r"output 'frames': expected frames \(16, 4, 5, C\), got \(17, 4, 5, 1\)"):
        Runner(pipeline, {}, Options(cache=CacheStore(tmp_path / "cache"))).run()


class Lookup(SequenceStage):
    """Maps frame indices through a YAML table (a ``file`` parameter); ``threads`` is out of the key."""

    name, version = "t.lookup", "1"
    inputs = {"rows": "rows"}
    outputs = {"mapped": "mapped"}
    params = (
        Param("table", str, "", "YAML list of values", file=True),
        Param("threads", int, 1, "does not change the output", in_key=False),
    )

    def run(self, inputs, params, ctx):
        table = np.asarray(yaml.safe_load(Path(params["table"]).read_text()))
        return {"mapped": {"value": table[inputs["rows"]["index"] % len(table)]}}


def test_file_params_key_on_content_and_out_of_key_params_reuse_the_entry(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # a relative path is read from the working directory
    Path("table.yaml").write_text("[1, 2, 3]\n")
    path = tmp_path / "p.yaml"
    path.write_text(
        "chunk_frames: 4\nstages:\n  ramp: {uses: t.ramp}\n"
        "  lookup: {uses: t.lookup, params: {table: table.yaml}, inputs: {rows: ramp.rows}}\n"
    )
    registry = Registry(classes=[Ramp, Lookup])

    def statuses(*overrides: str) -> dict[str, tuple[str, str]]:
        pipeline = load_pipeline(path, registry, overrides=list(overrides))
        options = Options(cache=CacheStore(tmp_path / "cache"))
        return {r.stage: (r.status, r.reason) for r in Runner(pipeline, {}, options).run()}

    assert statuses()["lookup"][0] == "ran"
    assert statuses("lookup.threads=4")["lookup"][0] == "cached"
    Path("table.yaml").write_text("[1, 2, 4]\n")
    planned = make_plan(load_pipeline(path, registry), {}, cache=CacheStore(tmp_path / "cache"), device="cpu")
    lookup = next(task for task in planned if task.stage == "lookup")
    assert lookup.status == "to compute" and "file of param table changed" in lookup.reason
    assert statuses()["lookup"][0] == "ran"


@pytest.mark.parametrize("own_prefix", ["t.ramp: ", "ramp: ", ""])
def test_a_stage_that_names_itself_is_named_once(own_prefix):
    from runner.config import StageNode, Where
    from runner.stage import StageError

    node = StageNode("ramp", "t.ramp", Ramp, {}, {}, Where("graph.yaml", 3, 3))
    failed = StageFailed(node, StageError(f"{own_prefix}no face in clip.mp4"))
    assert str(failed) == "stage 'ramp' (t.ramp): no face in clip.mp4"


class SlowRamp(Ramp):
    """:class:`Ramp` taking ``SLOW_S`` seconds a chunk (sleeping: the GIL is free)."""

    name = "t.slow_ramp"

    def process(self, start, stop, inputs, params, ctx):
        time.sleep(SLOW_S)
        return super().process(start, stop, inputs, params, ctx)


class Sums(SequenceStage):
    name, version = "t.sums", "1"
    inputs = {"frames": "frames"}
    outputs = {"sums": "sums"}

    def run(self, inputs, params, ctx):
        return {"sums": {"sum": np.array([int(chunk.sum()) for _, chunk in inputs["frames"].chunks()])}}


SLOW_S = 0.1


def test_stage_seconds_count_computing_not_waiting(tmp_path):
    """A stream of 6 chunks computed by two producer threads while `sums` reads it: `ramp`'s
    seconds are the wall time it computed (not the sum over both threads, twice that), and
    `sums` reports its own work, not the time it waited for the producers: no stage's seconds
    exceed the run's."""
    path = tmp_path / "p.yaml"
    path.write_text(
        "chunk_frames: 4\nstages:\n  ramp: {uses: t.slow_ramp}\n  sums: {uses: t.sums, inputs: {frames: ramp.frames}}\n"
    )
    pipeline = load_pipeline(path, Registry(classes=[SlowRamp, Sums]))
    started = time.perf_counter()
    reports = {r.stage: r for r in Runner(pipeline, {}, Options(cache=CacheStore(tmp_path / "cache"), producers=2)).run()}
    wall = time.perf_counter() - started
    assert reports["ramp"].status == reports["sums"].status == "ran"
    assert all(report.seconds <= wall for report in reports.values()), (reports, wall)
    assert reports["sums"].seconds < SLOW_S  # less than one chunk's computing: it only waited for them
