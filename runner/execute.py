"""Scheduling: run a validated pipeline against the cache (:mod:`runner.plan` says what a run would do).

Stages are visited in topological order, each once the stages it reads have had their turn. A
sequence stage is one cache entry. A frame stage is one entry per chunk of ``chunk_frames``
frames, and a :class:`FrameChunks` *resolves* each chunk once: its key (which resolves the
upstream chunks its window reads), then the stored entry, or compute, store and commit it under
the entry's lock. An entry keeps a chunk's bundles and files and the digests of its frames, not
the frames. So an interrupted run recomputes only the entries it had not finished.

When a chunk is resolved depends on who reads the stage:

- a cached frame stage that other stages read is resolved *lazily*: while readers are
  registered, a producer thread of its own computes its chunks in order
  (:meth:`FrameChunks.produce`), else each chunk is computed when a reader first needs it; each
  is handed to every registered reader (:class:`runner.broadcast.Broadcast`); the stages
  reading it while it is not resolved run on threads of their own at the same time
  (:mod:`runner.schedule`), so that decode -> gray ->
  write.video streams chunk by chunk and synthesize feeds its three writers at once; a reader
  that asks after the others passed a chunk gets it computed again;
- any other cached frame stage (no reader) resolves all its chunks at its turn, with
  ``--jobs`` threads;
- a frame stage declaring ``cached = False`` (decoding) stores no entry: its chunks are computed
  whenever they are read, and identified by their cache key instead of their bytes.

Every key (see :mod:`runner.digest`) includes the digests of the inputs actually used: a frame
stage's chunk depends on the upstream chunks its window overlaps, a sequence stage on the whole
upstream output. So a stage whose upstream re-ran but produced identical bytes is a cache hit.
A sequence stage reading a stream still being computed cannot know its key before the stream
is whole: it then either runs while the stream is computed (its key is taken at the end and
its entry committed, the first commit winning), or, when the first chunk computed now equals
what it read in its last completed run (the upstream's bytes are probably unchanged), waits for
the whole stream and looks its entry up first. See :meth:`Runner._read_while_computed`.

The pieces: keys in :mod:`runner.keys` and :mod:`runner.chunk_keys`, chunk resolution in
:mod:`runner.chunks`, storing and verified reading of entries in :mod:`runner.outputs`,
publishing in :mod:`runner.publish`, reports and timing in :mod:`runner.progress`.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.metadata
import os
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, ClassVar

from runner import notes
from runner.broadcast import unbounded
from runner.cache import CacheStore, Entry
from runner.chunk_keys import stream_info_key
from runner.chunks import FrameChunks, RunServices, Value, input_digests
from runner.config import ConfigError, Issue, Pipeline, StageNode, Where
from runner.depends import recording
from runner.digest import cache_key
from runner.errors import StageFailed, stage_errors
from runner.inputs import Inputs
from runner.keys import Keys
from runner.lifecycle import Lifecycle
from runner.outputs import Damaged, entry_context, load_bundle, read_or_redo, save_outputs, verify_files
from runner.plan import selected
from runner.progress import Progress, Report
from runner.publish import Published, conflicts, publish, refused, remove_leftovers, unwritable
from runner.schedule import StreamingSchedule
from runner.stage import FrameStage, StageError, StreamInfo, defines_stream_info
from runner.timing import own_time

__all__ = ["Options", "Report", "Runner", "StageFailed", "resolve_device"]


@dataclass
class Options:
    cache: CacheStore
    device: str = "cpu"
    jobs: int = 1
    producers: int | None = None  # threads computing a streamed lazy stage's chunks; None: os.cpu_count()
    force: frozenset[str] = frozenset()
    until: tuple[str, ...] = ()  # run only these stages and those they depend on; empty: every stage
    out: Path | None = None
    progress: bool = False
    log: Callable[[dict[str, Any]], None] = lambda event: None
    echo: Callable[[str], None] = lambda line: None
    warn: Callable[[str], None] = lambda line: None  # one line on stderr (a damaged cache entry)
    offload: bool = False  # a stage reading a source's frames and its branch run in a child process (runner.offload)
    overrides: tuple[str, ...] = ()  # the pipeline's --set overrides (for those child processes)


def resolve_device(requested: str) -> str:
    """``cpu`` or ``cuda`` for ``--device``; ``auto`` picks CUDA when torch can use it. A CPU-only
    torch build (version ``+cpu``) or no torch at all resolves without importing torch."""
    if requested != "auto":
        return requested
    try:
        version = importlib.metadata.version("torch")
    except importlib.metadata.PackageNotFoundError:
        return "cpu"
    if version.endswith("+cpu"):
        return "cpu"
    import torch  # only here: importing torch costs a second of start-up

    return "cuda" if torch.cuda.is_available() else "cpu"


class Runner:
    """The streaming executor: runs one pipeline with bound inputs; :meth:`run` returns one
    :class:`Report` per stage. :class:`runner.serial.SerialExecutor` is the same run without
    streaming (``streaming`` false): the reference its outputs and entries are tested against."""

    streaming: ClassVar[bool] = True  # lazy frame stages, stages on threads, producers, read-ahead, offload

    def __init__(self, pipeline: Pipeline, bound: dict[str, Path], options: Options):
        self.pipeline = pipeline
        self.opts = options
        self.store = options.cache
        self.values: dict[tuple[str | None, str], Value] = {}
        self.inputs = Inputs(pipeline, bound)
        for name, path in bound.items():
            self.values[(None, name)] = Value(pipeline.inputs[name].type, self.inputs.digest(name), load=lambda p=path: Path(p))
        self.entries: dict[str, list[Entry]] = {}  # per stage, its entries (one per chunk of a frame stage)
        self.redo: dict[str, Callable[[int], Entry]] = {}  # per stage, recompute its entry i (found damaged)
        self.keys = Keys(self.store, pipeline.path, device=options.device, chunk_frames=pipeline.chunk_frames)
        lock = threading.Lock()  # stages on several threads log events
        self._stopping = threading.Event()
        self._scheduler = threading.current_thread()

        def log(event: dict[str, Any]) -> None:
            if self._stopping.is_set() and threading.current_thread() is not self._scheduler:
                raise KeyboardInterrupt  # the run was interrupted: a stage on a thread stops here
            with lock:
                options.log(event)

        self.log = log
        self.progress = Progress(log=log, warn=options.warn, bars=options.progress)
        self.services = RunServices(
            self.keys,
            self.store,
            self.progress,
            options.jobs if self.streaming else 1,
            self.inputs,
            producers=options.producers or os.cpu_count() or 1,
            read_ahead=self.streaming,
        )
        self._lazy: list[FrameChunks] = []  # lazy frame stages not reported yet
        self._frame_stages: list[FrameChunks] = []  # every frame stage set up, closed at the run's end
        self._joined: dict[str, list[tuple[FrameChunks, str, threading.Thread]]] = {}  # per stage, the readers it registered
        self._producers: dict[FrameChunks, None] = {}  # lazy frame stages given a producer thread (ordered set)
        self._bound = bound
        self._in_child: dict[str, tuple[float, float]] = {}  # stages a child process ran: (seconds, CPU seconds)

    def selected(self) -> list[StageNode]:
        return selected(self.pipeline, self.opts.until)

    def run(self) -> list[Report]:
        """Run every selected stage, then publish.

        Raises
        ------
        ConfigError
            ``--out`` is a filesystem root, the home folder or the project's own, cannot be
            written, or holds something at a stage's folder that no earlier publish wrote
            (checked before anything runs).
        StageFailed
            A stage failed, or writing the cache or ``--out`` failed (disk full: the message
            names the stage and the file).
        """
        self.store.keep_library_files()
        with notes.showing():  # each distinct warning line once on stderr
            try:
                return self._run()
            finally:  # after publishing, which may compute a damaged entry again
                self._close_frame_stages()

    def _run(self) -> list[Report]:
        publishing = [node for node in self.selected() if "files" in node.cls.outputs.values()]
        if self.opts.out is not None and publishing:
            problem = refused(self.opts.out) or unwritable(self.opts.out)
            problems = [(self.opts.out, problem)] if problem else conflicts(self.opts.out, [n.name for n in publishing])
            if problems:
                raise ConfigError([Issue(Where("--out"), str(path), why) for path, why in problems])
            remove_leftovers(self.opts.out)
        reports: list[Report] = []

        def emit(report: Report) -> None:
            self.log({"event": "stage", **asdict(report)})
            self.opts.echo(report.line())
            reports.append(report)

        try:
            self._schedule(emit)
            for chunks in self._lazy:  # chunks no reader needed (normally none)
                chunks.resolve_all()
            for finished in self._finished_lazy():
                emit(finished)
        finally:
            for chunks in self._producers:
                chunks.stop_producing()
            for chunks in self._lazy:
                chunks.close()
        if self.opts.out is not None:
            for node in publishing:
                if self.entries.get(node.name):
                    self._publish(node, emit)
        self.store.break_stale_locks()
        return reports

    def _publish(self, node: StageNode, emit: Callable[[Report], None]) -> None:
        """Publish ``node``'s ``files`` outputs to ``--out``. A stage whose entries publishing
        found damaged and computed again is reported again, as ran, with the time that took."""
        ports = [p for p, kind in node.cls.outputs.items() if kind == "files"]
        item = Published(node.name, node.uses, ports, self.entries[node.name], self.redo[node.name])
        damaged: list[Damaged] = []

        def on_damaged(exc: Damaged) -> None:
            damaged.append(exc)
            self.progress.damaged(node, exc)

        started = time.perf_counter()
        with stage_errors(node):
            publish(self.opts.out, item, records=self.store.published_dir, on_damaged=on_damaged)
        if damaged:
            entries = "entry" if len(damaged) == 1 else "entries"
            reason = f"computed again to publish: {len(damaged)} damaged cache {entries}"
            emit(Report(node.name, node.uses, "ran", reason, seconds=time.perf_counter() - started))

    def _close_frame_stages(self) -> None:
        """Close every frame stage that computed a chunk (:meth:`runner.stage.Stage.close`),
        each even if closing another failed; the first failure is raised."""
        with contextlib.ExitStack() as closing:
            for chunks in reversed(self._frame_stages):
                closing.callback(lambda c=chunks: self._close_stage(c))

    @staticmethod
    def _close_stage(chunks: FrameChunks) -> None:
        with stage_errors(chunks.node):
            chunks.close_stage()

    def _schedule(self, emit: Callable[[Report], None]) -> None:
        """Visit every selected stage (:class:`runner.schedule.StreamingSchedule`)."""
        self._scheduler = threading.current_thread()
        StreamingSchedule(self, emit).schedule()

    def child_runner(self, stages: list[str], **events: Any) -> Runner:
        """The run a forked child process makes of ``stages`` (:mod:`runner.offload`), on this
        run's cache folder; ``events`` are its event callbacks (``log``, ``echo``, ``warn``)."""
        return Runner(
            self.pipeline,
            self._bound,
            Options(cache=CacheStore(self.store.root), device=self.opts.device, until=tuple(stages), **events),
        )

    def _sets_up_only(self, node: StageNode) -> bool:
        """True for a frame stage whose turn computes nothing: uncached, or lazy (read by a
        selected stage)."""
        return issubclass(node.cls, FrameStage) and (not node.cls.cached or self._is_read(node))

    def _leave(self, node: StageNode) -> None:
        """Unregister the readers ``node`` registered (it reads no more streams as computed)."""
        for chunks, reader, thread in self._joined.pop(node.name, []):
            chunks.broadcast.leave(reader, thread)

    def _visit(self, node: StageNode) -> Report | None:
        """Run one stage; its report, or None for a lazy frame stage (reported once
        its chunks are resolved)."""
        self.progress.current = node.name
        self.log({"event": "stage_start", "stage": node.name, "uses": node.uses})
        spent: list[tuple[float, float]] = []
        with own_time(lambda wall, cpu: spent.append((wall, cpu))), stage_errors(node):
            if issubclass(node.cls, FrameStage):
                report = self._frame_stage(node)
            else:
                report = self._sequence_stage(node)
        self.progress.current = None
        if report is not None:
            report.seconds += spent[0][0]
            report.cpu_seconds += spent[0][1]
            if node.name in self._in_child and report.status == "cached":
                report.status, report.reason = "ran", "in a child process beside the run"
                report.seconds, report.cpu_seconds = self._in_child[node.name]
        return report

    def _stream_reads(self, node: StageNode) -> tuple[bool, list[tuple[FrameChunks, str]]]:
        """Whether ``node`` runs on a thread of its own (it is a sequence stage or an eager
        frame stage reading a lazy frame stage that is not resolved yet), and the readers to
        register with those streams' broadcasts: ``node`` for the streams it reads, and each
        frame stage computed while ``node`` reads it (lazy, or uncached such as
        ``preview.side_by_side``) for its own inputs."""
        joins: list[tuple[FrameChunks, str]] = []
        threaded = False

        def walk(stage: StageNode, reader: str) -> None:
            nonlocal threaded
            for ref in stage.inputs.values():
                value = self.values.get((ref.stage, ref.port))
                if value is None or value.chunks is None:
                    continue
                producer = value.chunks
                if producer.node.cls.cached:
                    if not producer.lazy or producer.complete():
                        continue
                    threaded = True
                    if value.type == "frames":
                        joins.append((producer, reader))
                walk(producer.node, producer.node.name)  # computed while read: it reads its inputs then

        if self._sets_up_only(node):
            return False, []
        walk(node, node.name)
        return threaded, joins

    def _finished_lazy(self) -> list[Report]:
        """Reports of the lazy frame stages whose chunks are now all resolved."""
        done = [chunks for chunks in self._lazy if chunks.complete()]
        self._lazy = [chunks for chunks in self._lazy if chunks not in done]
        return [chunks.finish() for chunks in done]

    # -- inputs ----------------------------------------------------------------------------

    def _inputs(self, node: StageNode) -> dict[str, Value]:
        return {port: self.values[(ref.stage, ref.port)] for port, ref in node.inputs.items()}

    # -- sequence stages -------------------------------------------------------------------

    def _sequence_stage(self, node: StageNode) -> Report:
        inputs = self._inputs(node)
        forced = node.name in self.opts.force
        report = Report(node.name, node.uses, "cached")
        pending = {port: v for port, v in inputs.items() if v.known_digest() is None}
        streaming = bool(pending) and (forced or self._read_while_computed(node, pending))
        if pending and not streaming:  # resolving its inputs first: it reads no chunk as computed
            self._leave(node)
        key = None if streaming else cache_key(self.keys.material(node, input_digests(inputs)))
        entry = None if forced or key is None else self.keys.lookup(node, key)
        if entry is None:
            entry, ran = self._run_sequence(node, inputs, key, forced)
            report.status = "ran" if ran else "cached"
        if report.status == "cached":
            self.progress.replay(node.name, entry.record)
        if streaming:
            names = ", ".join(dict.fromkeys(node.inputs[port].stage for port in pending))
            report.reason = f"read {names} while it was computed"
        self.store.touch(entry)
        streams = {
            port: v.chunks.digests(v.port, 0, len(v.chunks.ranges) - 1)
            for port, v in inputs.items()
            if v.chunks is not None and v.type == "frames"
        }
        self.keys.remember(node, {**self.keys.material(node, input_digests(inputs)), "input_chunks": streams})
        self._set_outputs(node, entry, inputs)
        return report

    def _read_while_computed(self, node: StageNode, pending: dict[str, Value]) -> bool:
        """Whether sequence stage ``node`` runs while its ``pending`` inputs (streams not all
        stored yet) are computed, instead of after them.

        Its key needs their whole digests, so running first means running even when its entry
        exists (an upstream stage re-ran and produced identical bytes). Hence: compute the
        first missing chunk of each pending stream now and compare it with the same chunk in
        the stage's last completed run (or the first one the stream's producer thread computed
        already); run while computed if one differs (the key changes), else resolve everything
        first and look the entry up. With no last completed run reading that stream there is
        nothing to compare with: run while computed, without computing that chunk first.
        """
        read = (self.keys.memo(node) or {}).get("input_chunks", {})
        for port, v in pending.items():
            if v.type != "frames":
                continue
            count = len(v.chunks.ranges)
            first = next((i for i in range(count) if v.chunks.computed(i) or v.chunks.known_digests(v.port, i, i) is None), None)
            if first is None:
                continue
            if port not in read:
                return True
            # Not waiting for the other readers: they may be waiting for this one, registered at
            # chunk 0; the chunks they computed before (at most the broadcast's keep) are held.
            with unbounded():
                now = v.chunks.digests(v.port, first, first)
            if read.get(port, [])[first : first + 1] != now:
                return True
        return False

    def _run_sequence(self, node: StageNode, inputs: dict[str, Value], key: str | None, forced: bool) -> tuple[Entry, bool]:
        """Run a sequence stage under its entry's lock and commit its entry; with ``key`` None
        (inputs computed while read) the key is taken after the run, and the first commit of
        that key wins. Returns the entry and whether this run computed it."""
        frames = next((v.info.frames for v in inputs.values() if v.info is not None), None)
        lock = contextlib.nullcontext() if key is None else self.store.locked(key, on_wait=self.progress.waiting(node))
        with self.progress.bar(node, frames) as bar, lock:
            entry = None if forced or key is None else self.keys.lookup(node, key)
            if entry is not None:
                return entry, False
            with self.store.writing(key or f"pending-{node.name}") as tmp:
                values, params = {port: v.get(node.name) for port, v in inputs.items()}, dict(node.params)
                ctx = entry_context(tmp, device=self.opts.device, progress=bar.update)
                stage = node.cls()
                life = Lifecycle(stage, device=self.opts.device)
                try:
                    with recording(set()) as files, notes.recording() as warned:
                        result = life.call(values, params, lambda: stage.run(values, params, ctx))
                finally:
                    life.close()
                record = save_outputs(node.cls.outputs, result, tmp, frames=None)
                if key is None:
                    key = cache_key(self.keys.material(node, input_digests(inputs)))
                self.inputs.check(node.name)
                return self.store.commit(
                    key,
                    tmp,
                    {"stage": node.name, "uses": node.uses, **record, "depends": self.keys.depends(files), "warnings": warned},
                    replace=forced,
                ), True

    # -- frame stages ----------------------------------------------------------------------

    def _frame_stage(self, node: StageNode) -> Report | None:
        inputs = self._inputs(node)
        forced = node.name in self.opts.force
        stage = node.cls()
        info = self._stream_info(node, stage, inputs)
        counts = {port: v.info.frames for port, v in inputs.items() if v.type == "frames" and v.info is not None}
        if any(count != info.frames for count in counts.values()):
            with stage_errors(node):
                raise StageError(
                    f"its output stream has {info.frames} frames, its frames inputs {counts}: a frame "
                    f"stage computes output frame t from input frames t ± window (its size may differ)"
                )
        lazy = self.streaming and node.cls.cached and self._is_read(node)
        chunks = FrameChunks(self.services, node, stage, inputs, info, forced=forced, lazy=lazy, keep=self._keep(node))
        self._frame_stages.append(chunks)
        self.entries[node.name], self.redo[node.name] = chunks.entries, chunks.redo
        for port, kind in node.cls.outputs.items():
            load = None if kind == "frames" else (lambda p=port: chunks.load(p))
            self.values[(node.name, port)] = Value(kind, load=load, chunks=chunks, port=port, info=info)
        if not node.cls.cached:
            return Report(node.name, node.uses, "on demand", "computed while downstream stages read it", frames=info.frames)
        if lazy:
            self._lazy.append(chunks)
            return None
        chunks.resolve_all()
        return chunks.finish()

    def _keep(self, node: StageNode) -> int:
        """How many chunks of ``node`` may be computed past its slowest reader's position: the
        chunks one read spans (the largest window of a frame stage reading it, each side),
        and two more so that readers of different speeds overlap."""
        window = max(
            (
                other.cls.window
                for other in self.selected()
                if issubclass(other.cls, FrameStage) and any(ref.stage == node.name for ref in other.inputs.values())
            ),
            default=0,
        )
        return 3 + 2 * -(-window // self.pipeline.chunk_frames)

    def _is_read(self, node: StageNode) -> bool:
        """True if a selected stage reads one of ``node``'s outputs."""
        return any(ref.stage == node.name for other in self.selected() for ref in other.inputs.values())

    def _stream_info(self, node: StageNode, stage: FrameStage, inputs: dict[str, Value]) -> StreamInfo:
        """The stage's output stream shape: taken from the frames input, unless the stage
        computes it itself: then stored in the cache (:func:`runner.chunk_keys.stream_info_key`:
        keyed on its frame inputs' shapes, whose digests would resolve every chunk before
        anything reads them) so that it is computed once, and the planner finds it."""
        if not defines_stream_info(node.cls):
            return next(v.info for port, v in inputs.items() if node.cls.inputs[port] == "frames" and v.info is not None)
        streams = {port: v.info for port, v in inputs.items() if v.type == "frames" and v.info is not None}
        plain = {port: v.resolved_digest() for port, v in inputs.items() if port not in streams}
        key = stream_info_key(self.keys.material(node, plain), streams)
        entry = self.store.lookup(key)
        if entry is None:
            with notes.recording() as warned:
                info = stage.stream_info({port: v.get() for port, v in inputs.items()}, dict(node.params))
            self.inputs.check(node.name)
            with self.store.writing(key) as tmp:
                entry = self.store.commit(
                    key, tmp, {"stage": node.name, "uses": node.uses, "info": asdict(info), "warnings": warned}
                )
        else:
            self.store.touch(entry)  # used: kept by `gc --older-than` as long as its chunks
            self.progress.replay(node.name, entry.record)
        return StreamInfo(**entry.record["info"])

    # -- outputs ---------------------------------------------------------------------------

    def _set_outputs(self, node: StageNode, entry: Entry, inputs: dict[str, Value]) -> None:
        """Hand a sequence stage's stored outputs to downstream stages (read, verified, when
        first needed; a damaged entry is recomputed from ``inputs``)."""
        self.entries[node.name] = [entry]

        def redo(index: int) -> Entry:
            self.store.discard(self.entries[node.name][index])
            with stage_errors(node):
                self.entries[node.name][index] = self._run_sequence(node, inputs, entry.key, forced=False)[0]
            return self.entries[node.name][index]

        self.redo[node.name] = redo
        for port, kind in node.cls.outputs.items():
            read = (lambda e, p=port: verify_files(e, p)) if kind == "files" else (lambda e, p=port: load_bundle(e, p))
            self.values[(node.name, port)] = Value(
                kind, entry.record["outputs"][port]["digest"], lambda r=read: self._read_stored(node, r)
            )

    def _read_stored(self, node: StageNode, read: Callable[[Entry], Any]) -> Any:
        """``read`` of a sequence stage's entry, recomputing it if it is damaged."""
        return read_or_redo(
            read,
            self.entries[node.name][0],
            redo=lambda: self.redo[node.name](0),
            on_damaged=lambda exc: self.progress.damaged(node, exc),
        )
