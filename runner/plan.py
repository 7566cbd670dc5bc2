"""Planning: what a run of a pipeline would do, from its inputs and the cache alone.

:func:`make_plan` visits the selected stages in the order a run visits them and gives each a
:class:`Task`: its entry keys (one per chunk of a frame stage, one for a sequence stage), whether
each is stored, and why it would run. Nothing is computed: the keys are those a run computes
(:mod:`runner.keys`, :mod:`runner.chunk_keys`) from the digests of stored entries. Where a key
reads the output of a stage that would run, it is not known until that stage runs; the task then
names those stages. ``runner run --dry-run`` prints the plan.

A frame stage's chunks are those of its output stream. Its shape is that of its frames input,
or, for a stage computing its own (``stream_info``), the shape a run stored; a stage reading only
pipeline inputs (decoding: a probe of the clip's header) is asked for it, which reads inputs and
runs no stage computation. A shape neither stored nor read so means the stage has not run with
these inputs and parameters (a run stores the shape before any chunk): it would run, its keys
known once it runs (they read the shape), its chunks those of its frames inputs (a frame stage
keeps their frame count, :class:`runner.stage.FrameStage`), if it has any.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from runner.cache import CacheStore, Entry
from runner.chunk_keys import chunk_key, port_digest, stream_digest, stream_info_key, window_chunks
from runner.config import Pipeline, StageNode
from runner.digest import cache_key
from runner.errors import stage_errors
from runner.inputs import Inputs
from runner.keys import Keys
from runner.progress import Report
from runner.stage import FrameStage, StreamInfo, defines_stream_info
from runner.streams import chunk_ranges

Status = Literal["cached", "to compute", "forced", "unknown", "on demand"]

_REPORTED: dict[Status, str] = {
    "cached": "cached",
    "to compute": "will run",
    "forced": "will run",
    "unknown": "may run",
    "on demand": "on demand",
}


@dataclass(frozen=True)
class Task:
    """What a run would do for one stage.

    ``status``: ``cached`` (every entry stored), ``to compute`` (an entry missing), ``forced``
    (``--force``), ``unknown`` (a key reads the output of the stages ``after``, which would run
    first), ``on demand`` (an uncached frame stage: computed as read, stores no chunk).
    ``keys`` are its entry keys (per chunk of a frame stage; empty while a key reads what is
    known only once a stage runs), ``stored`` whether each is in the cache, ``chunks`` its chunk ranges ``(start, stop)`` in frames (a frame
    stage whose stream shape is known) and ``frames`` its frame count.
    """

    stage: str
    uses: str
    status: Status
    reason: str
    keys: tuple[str, ...] = ()
    stored: tuple[bool, ...] = ()
    chunks: tuple[tuple[int, int], ...] | None = None
    frames: int | None = None
    after: tuple[str, ...] = ()

    def report(self) -> Report:
        """The dry run's line for this task: cached / will run / may run / on demand."""
        counted = self.chunks is not None and self.status != "on demand"
        return Report(
            self.stage,
            self.uses,
            _REPORTED[self.status],
            self.reason,
            chunks=len(self.chunks) if counted and self.chunks is not None else None,
            chunks_cached=sum(self.stored),
            frames=self.frames,
        )


@dataclass(frozen=True)
class _Known:
    """An output (or pipeline input) as far as the plan knows it: its whole ``digest``; of a
    frame stream also the digests of its chunks and its shape. None: known once its stage ran."""

    digest: str | None
    chunks: list[str] | None = None
    info: StreamInfo | None = None


_UNKNOWN = _Known(None)


def selected(pipeline: Pipeline, until: tuple[str, ...]) -> list[StageNode]:
    """The stages a run visits, in the pipeline's order: every stage, or with ``until`` those
    stages and the ones they depend on."""
    names = set().union(*(pipeline.ancestors(name) for name in until)) if until else set(pipeline.stages)
    return [node for name, node in pipeline.stages.items() if name in names]


def visit_order(nodes: list[StageNode]) -> list[StageNode]:
    """``nodes`` (a pipeline's stages, each with the stages it reads) in the order a run on one
    thread visits them: each once the stages it reads are visited, the first such stage first."""
    waiting, done, order = list(nodes), set(), []
    while waiting:
        node = next(n for n in waiting if all(ref.stage is None or ref.stage in done for ref in n.inputs.values()))
        waiting.remove(node)
        done.add(node.name)
        order.append(node)
    return order


def make_plan(
    pipeline: Pipeline,
    bound: dict[str, Path],
    *,
    cache: CacheStore,
    device: str,
    force: frozenset[str] = frozenset(),
    until: tuple[str, ...] = (),
) -> list[Task]:
    """The tasks of a run of ``pipeline`` with inputs ``bound`` on ``device`` (the resolved
    one, part of every key), in the order a run visits the stages. Reads the cache, never
    writes it (a stale entry is reported, not removed)."""
    return _Planner(pipeline, bound, cache, device, force).plan(selected(pipeline, until))


class _Planner:
    def __init__(self, pipeline: Pipeline, bound: dict[str, Path], cache: CacheStore, device: str, force: frozenset[str]):
        self.pipeline, self.bound, self.store, self.force = pipeline, bound, cache, force
        self.keys = Keys(cache, pipeline.path, device=device, chunk_frames=pipeline.chunk_frames, discard_stale=False)
        inputs = Inputs(pipeline, bound)
        self.known: dict[tuple[str | None, str], _Known] = {(None, name): _Known(inputs.digest(name)) for name in bound}
        self.status: dict[str, Status] = {}  # per stage planned, its task's status

    def plan(self, nodes: list[StageNode]) -> list[Task]:
        tasks = []
        for node in visit_order(nodes):
            cls = node.cls
            task = self._frame_stage(node, cls) if issubclass(cls, FrameStage) else self._sequence_stage(node)
            self.status[node.name] = task.status
            tasks.append(task)
        return tasks

    def _inputs(self, node: StageNode) -> dict[str, _Known]:
        return {port: self.known[(ref.stage, ref.port)] for port, ref in node.inputs.items()}

    def _unknown(self, node: StageNode) -> Task | None:
        """The task of a stage reading an output not known until its stage runs, else None."""
        after = tuple(
            dict.fromkeys(
                ref.stage for ref in node.inputs.values() if ref.stage and self.known[(ref.stage, ref.port)].digest is None
            )
        )
        if not after:
            return None
        self._set_unknown(node)
        waits = ", ".join(f"{name} ({_REPORTED[self.status[name]]})" for name in after)
        reason = f"after {waits}; cached if what it reads is unchanged"
        return Task(node.name, node.uses, "unknown", reason, after=after)

    def _set_unknown(self, node: StageNode) -> None:
        for port in node.cls.outputs:
            self.known[(node.name, port)] = _UNKNOWN

    def _sequence_stage(self, node: StageNode) -> Task:
        unknown = self._unknown(node)
        if unknown is not None:
            return unknown
        material = self.keys.material(node, _digests(self._inputs(node)))
        key = cache_key(material)
        if node.name in self.force:
            self._set_unknown(node)
            return Task(node.name, node.uses, "forced", "forced (--force)", (key,), (False,))
        entry = self.keys.lookup(node, key)
        if entry is None:
            self._set_unknown(node)
            return Task(node.name, node.uses, "to compute", self.keys.why(node, material), (key,), (False,))
        for port in node.cls.outputs:
            self.known[(node.name, port)] = _Known(entry.record["outputs"][port]["digest"])
        return Task(node.name, node.uses, "cached", "cache hit", (key,), (True,))

    def _frame_stage(self, node: StageNode, cls: type[FrameStage]) -> Task:
        unknown = self._unknown(node)
        if unknown is not None:
            return unknown
        inputs = self._inputs(node)
        info = self._stream_info(node, cls, inputs)
        if info is None:
            return self._shape_unknown(node, cls, inputs)
        ranges = chunk_ranges(info.frames, self.pipeline.chunk_frames)
        plain = _digests({port: v for port, v in inputs.items() if v.chunks is None})
        material = self.keys.material(node, plain)
        keys = tuple(self._chunk_key(cls.window, material, chunk, info, inputs) for chunk in ranges)

        def task(status: Status, reason: str, stored: tuple[bool, ...] = ()) -> Task:
            return Task(node.name, node.uses, status, reason, keys, stored, tuple(ranges), info.frames)

        if not cls.cached:
            self._set_chunks(node, list(keys), info)
            return task("on demand", "computed while downstream stages read it")
        if node.name in self.force:
            self._set_unknown(node)
            return task("forced", "forced (--force)", (False,) * len(keys))
        entries = [self.keys.lookup(node, key) for key in keys]
        stored = tuple(entry is not None for entry in entries)
        found = [entry for entry in entries if entry is not None]
        if len(found) == len(entries):
            self._set_chunks(node, found, info)
            return task("cached", "cache hit", stored)
        self._set_unknown(node)
        if found:
            reason = f"{len(entries) - len(found)} of {len(entries)} chunks missing (earlier run incomplete)"
        else:
            reason = self.keys.why(node, self.keys.material(node, _digests(inputs)))
        return task("to compute", reason, stored)

    def _shape_unknown(self, node: StageNode, cls: type[FrameStage], inputs: dict[str, _Known]) -> Task:
        """The task of a frame stage whose stream shape is not stored: it has not run with these
        inputs and parameters (a run stores the shape first), so it would run; its keys read the
        shape, known once it runs; its chunks are those of its frames inputs, if any (a frame
        stage keeps their frame count)."""
        self._set_unknown(node)
        frames = next((v.info.frames for v in inputs.values() if v.info is not None), None)
        chunks = None if frames is None else tuple(chunk_ranges(frames, self.pipeline.chunk_frames))
        if not cls.cached:
            return Task(
                node.name, node.uses, "on demand", "computed while downstream stages read it", chunks=chunks, frames=frames
            )
        if node.name in self.force:
            return Task(node.name, node.uses, "forced", "forced (--force)", chunks=chunks, frames=frames)
        reason = self.keys.why(node, self.keys.material(node, _digests(inputs)))
        return Task(node.name, node.uses, "to compute", reason, chunks=chunks, frames=frames)

    def _set_chunks(self, node: StageNode, chunks: list[Entry] | list[str], info: StreamInfo) -> None:
        """Make a frame stage's outputs known from its chunks' entries (or keys, uncached)."""
        for port, kind in node.cls.outputs.items():
            digests = [port_digest(port, chunk) for chunk in chunks]
            whole = stream_digest(digests, info)
            self.known[(node.name, port)] = _Known(whole, digests, info) if kind == "frames" else _Known(whole)

    def _chunk_key(
        self, window: int, material: dict[str, Any], chunk: tuple[int, int], info: StreamInfo, inputs: dict[str, _Known]
    ) -> str:
        """Key of one chunk (:func:`runner.chunk_keys.chunk_key`) from the known digests of what it reads."""
        streams: dict[str, tuple[StreamInfo, list[str]]] = {}
        for port, v in inputs.items():
            if v.chunks is not None and v.info is not None:
                lo, hi = window_chunks(chunk, window=window, frames=v.info.frames, chunk_frames=self.pipeline.chunk_frames)
                streams[port] = (v.info, v.chunks[lo : hi + 1])
        return chunk_key(material, chunk, info, streams)

    def _stream_info(self, node: StageNode, cls: type[FrameStage], inputs: dict[str, _Known]) -> StreamInfo | None:
        """The stage's output stream shape (see the module's docstring), None if not known."""
        streams = {port: v.info for port, v in inputs.items() if v.info is not None}
        if not defines_stream_info(cls):
            return next(iter(streams.values()))
        plain = _digests({port: v for port, v in inputs.items() if v.info is None})
        entry = self.store.lookup(stream_info_key(self.keys.material(node, plain), streams))
        if entry is not None:
            return StreamInfo(**entry.record["info"])
        if any(ref.stage is not None for ref in node.inputs.values()):
            return None
        with stage_errors(node):  # a clip that cannot be read: one line, as in a run
            return cls().stream_info({port: self.bound[ref.port] for port, ref in node.inputs.items()}, dict(node.params))


def _digests(inputs: dict[str, _Known]) -> dict[str, str]:
    """Digest per input port (every one known: the stage's inputs are planned)."""
    return {port: v.digest for port, v in inputs.items() if v.digest is not None}
