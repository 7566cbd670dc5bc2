"""Cached frame stages computed while the stages reading them run at the same time: each chunk
is computed once and handed to both readers, who never fall more than the broadcast's ``keep``
chunks behind; entries record the frames' digests, not the frames; a second run is a cache hit;
an interrupted stream resumes with the missing entries only; and a reader whose input bytes did
not change stays a cache hit. Ground truth: numpy on the ramp clip.
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


class Picker(SequenceStage):
    """Reads single frames here and there (like a contact sheet): ``read(f, f + 1)``."""

    name, version = "s.picker", "1"
    inputs = {"frames": "frames"}
    outputs = {"all": "all"}
    params = (Param("frames", list, [2, 13, 21], "frames picked"),)

    def run(self, inputs, params, ctx):
        return {"all": {"frames": np.concatenate([inputs["frames"].read(f, f + 1) for f in params["frames"]])}}


REGISTRY = Registry(classes=[Source, Double, Reader, Picker])
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


def run(tmp_path: Path, *overrides: str, jobs: int = 1, extra: str = "") -> tuple[Runner, dict[str, Report]]:
    path = tmp_path / "p.yaml"
    path.write_text(textwrap.dedent(PIPELINE) + extra)
    pipeline = load_pipeline(path, REGISTRY, overrides=list(overrides))
    runner = Runner(pipeline, {}, Options(cache=CacheStore(tmp_path / "cache"), jobs=jobs))
    EVENTS.clear()
    return runner, {report.stage: report for report in runner.run()}


def _stored(tmp_path: Path, stage: str) -> list[int]:
    return sorted(
        e.record["range"][0]
        for e in CacheStore(tmp_path / "cache").iter_entries()
        if e.record.get("stage") == stage and "range" in e.record
    )


def _reads_before(events: list[tuple[str, int]], reader: str, upto: int) -> int:
    return sum(1 for what, _ in events[:upto] if what == reader)


@pytest.mark.parametrize("jobs", [1, 3])
def test_chunks_are_computed_once_and_handed_to_both_readers(tmp_path, jobs):
    runner, reports = run(tmp_path, jobs=jobs)
    for stage in ("source", "double"):
        assert sorted(start for what, start in EVENTS if what == stage) == STARTS  # once each
    for reader in ("first", "second"):
        assert [start for what, start in EVENTS if what == reader] == STARTS
        np.testing.assert_array_equal(runner.values[(reader, "all")].get()["frames"], 2 * clip())
    # Bounded memory: double's chunk k is computed only once each reader has read chunk
    # k - keep, give or take the one chunk a reader computes before it starts reading (to
    # guess whether its key changes, see docs/runner.md).
    keep = runner.values[("double", "frames")].chunks.broadcast.keep
    for index, (what, start) in enumerate(EVENTS):
        if what == "double":
            for reader in ("first", "second"):
                assert _reads_before(EVENTS, reader, index) >= start // 4 - keep
    # Entries hold the chunks' digests, not their frames.
    assert _stored(tmp_path, "source") == _stored(tmp_path, "double") == STARTS
    assert not list((tmp_path / "cache" / "entries").rglob("*.npy"))
    assert set(reports) == {"source", "double", "first", "second"}
    for stage in ("source", "double"):
        report = reports[stage]
        assert (report.status, report.chunks, report.chunks_cached, report.frames) == ("ran", 6, 0, N)
    for reader in ("first", "second"):
        # With keep >= the 6 chunks (jobs 3), the producer threads may compute them all before
        # the readers' turn: the readers then read them held, with double's digests known.
        streamed = reports[reader].reason == "read double while it was computed"
        assert reports[reader].status == "ran" and (streamed or keep >= len(STARTS))

    # A second run is a full cache hit: no stage computes or reads anything.
    _, reports = run(tmp_path)
    assert EVENTS == []
    assert {stage: r.status for stage, r in reports.items()} == dict.fromkeys(reports, "cached")


def test_interrupted_stream_resumes_with_missing_chunks_only(tmp_path):
    with pytest.raises(StageFailed, match=r"stage 'first' \(s.reader\): frame 9: cannot read"):
        run(tmp_path, "first.fail_at=9")
    # second read on: every chunk's entry is stored; the failed reader left no lock behind.
    assert _stored(tmp_path, "double") == STARTS and _stored(tmp_path, "source") == STARTS
    assert not list((tmp_path / "cache" / "locks").glob("*.lock"))
    runner, reports = run(tmp_path)
    # first runs again and needs frames: computed again from the stored entries, none stored twice.
    assert (reports["double"].status, reports["double"].chunks_cached) == ("cached", 6)
    assert reports["second"].status == "cached" and reports["first"].status == "ran"
    assert sorted(start for what, start in EVENTS if what == "double") == STARTS
    np.testing.assert_array_equal(runner.values[("first", "all")].get()["frames"], 2 * clip())


def test_reader_stays_cached_when_upstream_bytes_do_not_change(tmp_path):
    run(tmp_path)
    # `note` changes source's keys, not its bytes: source re-runs, double and the readers are hits.
    _, reports = run(tmp_path, "source.note=x")
    assert {stage: r.status for stage, r in reports.items()} == {
        "source": "ran",
        "double": "cached",
        "first": "cached",
        "second": "cached",
    }
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


def test_a_reader_picking_frames_later_gets_just_those_frames_computed_again(tmp_path):
    """After a run, a new stage picks three frames of double: neither source nor double stores
    frames, so each picked frame is computed again on its own (with source's frames around it,
    double's window), not its whole chunk, and equals the streamed frames."""
    run(tmp_path)
    runner, reports = run(tmp_path, extra="  pick: {uses: s.picker, inputs: {frames: double.frames}}\n")
    assert reports["pick"].status == "ran" and reports["double"].status == "cached"
    np.testing.assert_array_equal(runner.values[("pick", "all")].get()["frames"], 2 * clip()[[2, 13, 21]])
    assert [event for event in EVENTS if event[0] == "double"] == [("double", 2), ("double", 13), ("double", 21)]
