"""A lazy frame stage's chunks are computed in order by producer threads of their own, the
readers only take them (none computes a chunk the others wait for); a reader of a stage that
defines its own stream shape (like ``preview.side_by_side``) streams it, bounded, instead of
resolving the whole upstream first; a computed stream serves a reader behind the in-order
position without holding up the readers in order. Ground truth: numpy on the ramp clip."""

from __future__ import annotations

import threading

import numpy as np

from runner.registry import Registry
from runner.stage import FrameStage, StreamInfo
from runner.streams import ComputedStream, chunk_ranges
from tests.runner import test_streaming as streaming
from tests.runner.test_streaming import EVENTS, STARTS, Double, Picker, Reader, Source, clip, run

THREADS: list[tuple[str, int, str]] = []  # (stage, first frame, computing thread)


class Pair(FrameStage):
    """Uncached, defines its own stream shape from its frames input (as preview.side_by_side):
    each chunk's key reads the whole input stream. Output: the input frames plus one."""

    name, version, cached = "s.pair", "1", False
    inputs = {"frames": "frames"}
    outputs = {"frames": "frames"}

    def stream_info(self, inputs, params):
        return inputs["frames"].info

    def process(self, start, stop, inputs, params, ctx):
        return {"frames": inputs["frames"].read(start, stop) + 1}


class Traced(Double):
    name = "s.traced"

    def process(self, start, stop, inputs, params, ctx):
        THREADS.append(("double", start, threading.current_thread().name))
        return super().process(start, stop, inputs, params, ctx)


def test_producer_threads_compute_the_chunks_and_readers_only_take_them(tmp_path, monkeypatch):
    monkeypatch.setattr(streaming, "REGISTRY", Registry(classes=[Source, Traced, Reader, Picker]))
    monkeypatch.setattr(streaming, "PIPELINE", streaming.PIPELINE.replace("s.double", "s.traced"))
    THREADS.clear()
    runner, reports = run(tmp_path)
    assert sorted(start for _, start, _ in THREADS) == STARTS  # once each
    assert all(thread.startswith("produce-double-") for _, _, thread in THREADS)
    for reader in ("first", "second"):
        np.testing.assert_array_equal(runner.values[(reader, "all")].get()["frames"], 2 * clip())
    assert reports["double"].reason == "computed while first, second read it"


def test_reading_a_stage_that_defines_its_own_shape_streams_within_keep(tmp_path, monkeypatch):
    """first reads pair (uncached, each chunk keyed on all of double): before, its probe of
    pair's first chunk resolved every chunk of double before first read any (all held)."""
    monkeypatch.setattr(streaming, "REGISTRY", Registry(classes=[Source, Double, Reader, Pair]))
    monkeypatch.setattr(
        streaming,
        "PIPELINE",
        streaming.PIPELINE.replace(
            "  first: {uses: s.reader, inputs: {frames: double.frames}}",
            "  pair: {uses: s.pair, inputs: {frames: double.frames}}\n  first: {uses: s.reader, inputs: {frames: pair.frames}}",
        ),
    )
    runner, reports = run(tmp_path)
    np.testing.assert_array_equal(runner.values[("first", "all")].get()["frames"], 2 * clip() + 1)
    assert reports["first"].reason == "read pair while it was computed"
    keep = runner.values[("double", "frames")].chunks.broadcast.keep
    for index, (what, start) in enumerate(EVENTS):
        if what == "double":
            assert sum(1 for w, _ in EVENTS[:index] if w == "first") >= start // 4 - keep


def test_a_reader_behind_does_not_hold_up_the_reader_in_order():
    """Chunk 2 is being computed in order (blocked until released) while another thread asks
    for chunk 0, no longer kept: it is computed at once, outside the stream's lock."""
    frames = np.arange(10, dtype=np.uint8).reshape(10, 1, 1, 1)
    ranges = chunk_ranges(10, 4)
    release, in_order, calls = threading.Event(), threading.Event(), []

    def compute(i):
        calls.append(i)
        if i == 2:
            in_order.set()
            assert release.wait(30)
        return frames[slice(*ranges[i])]

    stream = ComputedStream(StreamInfo(10, 25.0, 1, 1), ranges, compute, keep=1)
    stream.chunk(0), stream.chunk(1)  # chunk 0 dropped (keep 1)
    ahead = threading.Thread(target=stream.chunk, args=(2,))
    ahead.start()
    assert in_order.wait(30)
    np.testing.assert_array_equal(stream.chunk(0), frames[0:4])  # would wait on the lock forever
    release.set()
    ahead.join()
    assert calls == [0, 1, 2, 0]
    np.testing.assert_array_equal(stream.chunk(2), frames[8:10])  # kept: not computed again
    assert calls == [0, 1, 2, 0]
