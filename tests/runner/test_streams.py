"""Frame streams: reads with edge replication match slicing a padded array; computed chunks are
produced in order and only once while they stay in memory."""

from __future__ import annotations

import numpy as np

from runner.stage import StreamInfo
from runner.streams import CachedStream, ComputedStream, chunk_ranges


def _clip(n: int) -> np.ndarray:
    return np.arange(n * 2 * 3 * 1, dtype=np.uint8).reshape(n, 2, 3, 1)


def test_chunk_ranges():
    assert chunk_ranges(10, 4) == [(0, 4), (4, 8), (8, 10)]
    assert chunk_ranges(0, 4) == []


def test_cached_stream_reads_across_chunks_with_edge_replication(tmp_path):
    clip = _clip(10)
    ranges = chunk_ranges(10, 4)
    files = []
    for s, e in ranges:
        np.save(tmp_path / f"{s}.npy", clip[s:e])
        files.append(tmp_path / f"{s}.npy")
    stream = CachedStream(StreamInfo(10, 25.0, 3, 2), ranges, files)
    padded = np.concatenate([clip[:1].repeat(3, 0), clip, clip[-1:].repeat(3, 0)])
    for start, stop in [(0, 10), (-3, 2), (3, 5), (7, 13), (-3, 13), (9, 10)]:
        np.testing.assert_array_equal(stream.read(start, stop), padded[start + 3:stop + 3])
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
