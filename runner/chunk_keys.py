"""The cache key of a frame stage's chunk and the digests of its outputs, computed from the
digests of what the chunk reads; the one description of it that the planner (:mod:`runner.plan`)
and the executors (:mod:`runner.chunks`) share.

A chunk of frames ``[start, stop)`` reads every input that is not a frame stream whole and, of
each frame stream, the upstream chunks that frames ``[start - window, stop + window)`` touch
(clamped to the clip): output frame t is computed from input frames t ± window, whatever size
the stage gives its frames (:class:`runner.stage.FrameStage`).
"""

from __future__ import annotations

import json
from dataclasses import asdict
from typing import Any

from runner.cache import Entry
from runner.digest import cache_key, combine
from runner.stage import StreamInfo


def window_chunks(chunk: tuple[int, int], *, window: int, frames: int, chunk_frames: int) -> tuple[int, int]:
    """The upstream chunks ``(lo, hi)`` (inclusive) that a chunk of frames ``chunk = (start,
    stop)`` reads from a stream of ``frames`` frames cut in chunks of ``chunk_frames``, with the
    reading stage's ``window`` (frames each side)."""
    start, stop = chunk
    return max(0, start - window) // chunk_frames, (min(frames, stop + window) - 1) // chunk_frames


def chunk_key(
    material: dict[str, Any],
    chunk: tuple[int, int],
    info: StreamInfo,
    streams: dict[str, tuple[StreamInfo, list[str]]],
) -> str:
    """Cache key of a chunk of frames ``chunk = (start, stop)`` of a stage whose output stream is
    ``info``: ``material`` is the stage's key material (:meth:`runner.keys.Keys.material`) with
    the digests of its inputs that are not frame streams; ``streams`` gives, per frame input,
    its stream shape and the digests of the upstream chunks the chunk reads (:func:`window_chunks`)."""
    return cache_key(
        {
            **material,
            "chunk": list(chunk),
            "info": asdict(info),
            "chunk_inputs": {port: {"info": asdict(shape), "chunks": digests} for port, (shape, digests) in streams.items()},
        }
    )


def port_digest(port: str, chunk: Entry | str) -> str:
    """Digest of output ``port`` in one chunk: from its entry (a cached stage), or from its key
    (an uncached stage's chunks are identified by their key, ``chunk`` a str)."""
    if isinstance(chunk, str):
        return cache_key({"computed": chunk, "port": port})
    digest: str = chunk.record["outputs"][port]["digest"]
    return digest


def stream_digest(digests: list[str], info: StreamInfo) -> str:
    """Digest of a whole output: the digests of its chunks and the stream shape."""
    return combine([*digests, json.dumps(asdict(info))])


def stream_info_key(material: dict[str, Any], streams: dict[str, StreamInfo]) -> str:
    """Key of the stored stream shape of a stage that computes its own (``stream_info``):
    ``material`` with the digests of its inputs that are not frame streams, and the shapes of
    its frame inputs (``streams``; their digests would need every upstream chunk resolved)."""
    extra: dict[str, Any] = {"input_streams": {port: asdict(info) for port, info in streams.items()}} if streams else {}
    return cache_key({**material, "stream_info": True, **extra})
