"""Cached frame stages computed while a downstream stage reads them: chunks of the upstream
stages are computed, stored and read interleaved, one at a time; a second reader and a second
run read the stored chunks; an interrupted stream resumes with the missing chunks only; and a
reader whose input bytes did not change stays a cache hit. Ground truth: numpy on the ramp clip.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest

from runner.cache import CacheStore
from runner.config import load_pipeline
from runner.execute import Options, Report, Runner, StageFailed
from runner.registry import Registry
from runner.stage import FrameStage, Param, SequenceStage, StageError, StreamInfo

N, H, W = 23, 4, 5  # 6 chunks of 4 frames
EVENTS: list[tuple[str, int]] = []  # (what, first frame) in the order the stages did it


def clip() -> np.ndarray:
    """Frame t is filled with t."""
    return np.broadcast_to(np.arange(N, dtype=np.uint16)[:, None, None, None], (N, H, W, 1)).copy()


class Source(FrameStage):
    """The ramp clip; ``bump_from`` adds 100 from that frame on; ``note`` changes only the key."""

    name, version = "s.source", "1"
    outputs = {"frames": "frames"}
    params = (Param("bump_from", int, N, "first frame bumped"), Param("note", str, "", "ignored"))

    def stream_info(self, inputs, params):
        return StreamInfo(N, 25.0, W, H)

    def process(self, start, stop, inputs, params, ctx):
        EVENTS.append(("source", start))
        frames = clip()[start:stop]
        return {"frames": frames + 100 * (np.arange(start, stop) >= params["bump_from"])[:, None, None, None]}


class Double(FrameStage):
    """2 x the frame, reading one frame of context each side (window 1)."""

    name, version, window = "s.double", "1", 1
    inputs = {"frames": "frames"}
    outputs = {"frames": "frames"}

    def process(self, start, stop, inputs, params, ctx):
        EVENTS.append(("double", start))
        return {"frames": 2 * inputs["frames"].read(start - 1, stop + 1)[1:-1]}


class Reader(SequenceStage):
    """Reads its stream chunk by chunk, logging each read under its ``tag``; ``fail_at`` raises
    after reading the chunk holding that frame."""

    name, version = "s.reader", "1"
    inputs = {"frames": "frames"}
    outputs = {"all": "all"}
    params = (Param("tag", str, "first", "name in the event log"), Param("fail_at", int, -1, "frame"))

    def run(self, inputs, params, ctx):
        parts = []
        for start, chunk in inputs["frames"].chunks():
            EVENTS.append((params["tag"], start))
            if start <= params["fail_at"] < start + len(chunk):
                raise StageError(f"frame {params['fail_at']}: cannot read")
            parts.append(chunk)
        return {"all": {"frames": np.concatenate(parts)}}


REGISTRY = Registry(classes=[Source, Double, Reader])
PIPELINE = """
chunk_frames: 4
stages:
  source: {uses: s.source}
  double: {uses: s.double, inputs: {frames: source.frames}}
  first: {uses: s.reader, inputs: {frames: double.frames}}
  second: {uses: s.reader, params: {tag: second}, inputs: {frames: double.frames}}
"""
STARTS = list(range(0, N, 4))


@pytest.fixture(autouse=True)
def _clear_events():
    EVENTS.clear()


def run(tmp_path: Path, *overrides: str, jobs: int = 1) -> tuple[Runner, dict[str, Report]]:
    path = tmp_path / "p.yaml"
    path.write_text(textwrap.dedent(PIPELINE))
    pipeline = load_pipeline(path, REGISTRY, overrides=list(overrides))
    runner = Runner(pipeline, {}, Options(cache=CacheStore(tmp_path / "cache"), jobs=jobs))
    EVENTS.clear()
    return runner, {report.stage: report for report in runner.run()}


def _stored(tmp_path: Path, stage: str) -> list[int]:
    return sorted(e.record["range"][0] for e in CacheStore(tmp_path / "cache").iter_entries()
                  if e.record.get("stage") == stage and "range" in e.record)


def test_upstream_chunks_are_computed_stored_and_read_interleaved(tmp_path):
    runner, reports = run(tmp_path)
    # double's chunk i reads source frames up to 4i + 4 (window 1): source runs one chunk ahead.
    expected = [("source", 0), ("source", 4), ("double", 0), ("first", 0)]
    for start in STARTS[1:]:
        expected += [("source", start + 4)] if start + 4 < N else []
        expected += [("double", start), ("first", start)]
    assert EVENTS[:len(expected)] == expected
    # The second reader reads the stored chunks: nothing is computed again.
    assert EVENTS[len(expected):] == [("second", start) for start in STARTS]
    for reader in ("first", "second"):
        np.testing.assert_array_equal(runner.values[(reader, "all")].get()["frames"], 2 * clip())
    assert _stored(tmp_path, "source") == _stored(tmp_path, "double") == STARTS
    # Summaries: chunks and frames of the streamed stages, reported before their readers.
    assert list(reports) == ["source", "double", "first", "second"]
    for stage in ("source", "double"):
        report = reports[stage]
        assert (report.status, report.chunks, report.chunks_cached, report.frames) == ("ran", 6, 0, N)
        assert report.reason == "computed while first read it"
    assert reports["first"].status == "ran" and reports["first"].reason == "read double while it was computed"
    assert reports["second"].status == "ran" and reports["second"].reason == ""

    # A second run is a full cache hit: no stage computes or reads anything.
    _, reports = run(tmp_path)
    assert EVENTS == []
    assert {stage: r.status for stage, r in reports.items()} == dict.fromkeys(reports, "cached")


def test_jobs_precompute_gives_the_same_entries(tmp_path):
    runner, _ = run(tmp_path, jobs=3)
    assert EVENTS.index(("first", 0)) > max(EVENTS.index(("double", s)) for s in STARTS)  # no streaming
    np.testing.assert_array_equal(runner.values[("first", "all")].get()["frames"], 2 * clip())
    _, reports = run(tmp_path)  # the streaming run finds every chunk stored
    assert EVENTS == [] and reports["double"].status == "cached"


def test_interrupted_stream_resumes_with_missing_chunks_only(tmp_path):
    with pytest.raises(StageFailed, match=r"stage 'first' \(s.reader\): frame 9: cannot read"):
        run(tmp_path, "first.fail_at=9")
    # The reader stopped in chunk 2: double has chunks 0-2, source one more (double's window).
    assert _stored(tmp_path, "double") == [0, 4, 8] and _stored(tmp_path, "source") == [0, 4, 8, 12]
    assert not list((tmp_path / "cache" / "locks").glob("*.lock"))
    runner, reports = run(tmp_path)
    computed = [event for event in EVENTS if event[0] in ("source", "double")]
    assert computed == [("source", 16), ("double", 12), ("source", 20), ("double", 16), ("double", 20)]
    assert (reports["double"].status, reports["double"].chunks_cached) == ("partial", 3)
    np.testing.assert_array_equal(runner.values[("first", "all")].get()["frames"], 2 * clip())


def test_reader_stays_cached_when_upstream_bytes_do_not_change(tmp_path):
    run(tmp_path)
    # `note` changes source's keys, not its bytes: source re-runs, double and the readers are hits.
    _, reports = run(tmp_path, "source.note=x")
    assert {stage: r.status for stage, r in reports.items()} == {
        "source": "ran", "double": "cached", "first": "cached", "second": "cached"}
    assert {what for what, _ in EVENTS} == {"source"}
    # Only the last chunk changes: the first chunk matches the readers' last run, so the stream
    # is resolved before they run (no streaming); they re-run on the new bytes.
    runner, reports = run(tmp_path, "source.bump_from=21")
    assert EVENTS.index(("first", 0)) > EVENTS.index(("double", 20))
    # double's chunk 16-20 reads source's last chunk (window 1): its key changes too.
    assert (reports["double"].status, reports["double"].chunks_cached) == ("partial", 4)
    assert reports["first"].status == "ran"
    truth = clip() + 100 * (np.arange(N) >= 21)[:, None, None, None]
    np.testing.assert_array_equal(runner.values[("second", "all")].get()["frames"], 2 * truth)
