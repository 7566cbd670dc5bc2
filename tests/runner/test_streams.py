"""Frame streams: reads with edge replication match slicing a padded array; computed chunks are
produced in order and only once while they stay in memory; read-ahead computes the next chunk
on one thread of its own, once, while the reader works, and hands its failures to the reader."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from runner.stage import StreamInfo
from runner.streams import ComputedStream, chunk_ranges
from tests.memory_stream import NpyStream


def _clip(n: int) -> np.ndarray:
    return np.arange(n * 2 * 3 * 1, dtype=np.uint8).reshape(n, 2, 3, 1)


def test_chunk_ranges():
    assert chunk_ranges(10, 4) == [(0, 4), (4, 8), (8, 10)]
    assert chunk_ranges(0, 4) == []


def test_chunked_stream_reads_across_chunks_with_edge_replication(tmp_path):
    clip = _clip(10)
    ranges = chunk_ranges(10, 4)
    files = []
    for s, e in ranges:
        np.save(tmp_path / f"{s}.npy", clip[s:e])
        files.append(tmp_path / f"{s}.npy")
    stream = NpyStream(StreamInfo(10, 25.0, 3, 2), ranges, files)
    padded = np.concatenate([clip[:1].repeat(3, 0), clip, clip[-1:].repeat(3, 0)])
    for start, stop in [(0, 10), (-3, 2), (3, 5), (7, 13), (-3, 13), (9, 10)]:
        np.testing.assert_array_equal(stream.read(start, stop), padded[start + 3 : stop + 3])
    assert [s for s, _ in stream.chunks()] == [0, 4, 8]
    np.testing.assert_array_equal(np.concatenate([c for _, c in stream.chunks()]), clip)


def test_computed_stream_computes_in_order_once():
    clip = _clip(10)
    ranges = chunk_ranges(10, 4)
    calls = []

    def compute(i):
        calls.append(i)
        s, e = ranges[i]
        return clip[s:e]

    stream = ComputedStream(StreamInfo(10, 25.0, 3, 2), ranges, compute, keep=2)
    np.testing.assert_array_equal(stream.read(5, 9), clip[5:9])  # chunks 1 and 2: computes 0, 1, 2
    np.testing.assert_array_equal(stream.read(4, 8), clip[4:8])
    assert calls == [0, 1, 2]
    np.testing.assert_array_equal(stream.read(0, 1), clip[0:1])  # evicted: recomputed
    assert calls == [0, 1, 2, 0]


def test_read_ahead_computes_the_next_chunk_once_on_one_thread_while_the_reader_works():
    clip = _clip(22)
    ranges = chunk_ranges(22, 4)
    calls, reading = [], threading.Event()
    overlapped = []

    def compute(i):
        if i > 0:  # the read-ahead's chunk is computed while the reader still holds the last one
            overlapped.append(reading.is_set())
        calls.append((i, threading.current_thread().name))
        s, e = ranges[i]
        return clip[s:e]

    stream = ComputedStream(StreamInfo(22, 25.0, 3, 2), ranges, compute, keep=2, read_ahead=True)
    got = []
    for start, frames in stream.chunks():
        reading.set()
        got.append(frames)
        for _ in range(10_000):  # the reader's own work on this chunk (at most 10 s)
            if len(calls) >= min(len(got) + 1, len(ranges)):
                break
            threading.Event().wait(0.001)
        reading.clear()
    np.testing.assert_array_equal(np.concatenate(got), clip)
    assert [i for i, _ in calls] == list(range(len(ranges)))  # each chunk once, in order
    assert calls[0][1] == threading.current_thread().name
    assert {name for _, name in calls[1:]} == {"read-ahead"}  # one thread: a decoder goes on where it was
    assert all(overlapped)


def test_read_ahead_failure_reaches_the_reader_of_that_chunk():
    ranges = chunk_ranges(12, 4)

    def compute(i):
        if i == 1:
            raise ValueError("frame 4 is corrupt")
        s, e = ranges[i]
        return _clip(12)[s:e]

    stream = ComputedStream(StreamInfo(12, 25.0, 3, 2), ranges, compute, keep=2, read_ahead=True)
    np.testing.assert_array_equal(stream.read(0, 4), _clip(12)[0:4])
    with pytest.raises(ValueError, match="frame 4 is corrupt"):
        stream.read(4, 8)
