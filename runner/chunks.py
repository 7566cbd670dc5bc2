"""The chunks of one frame stage in one run (:class:`FrameChunks`), and the values stages hand
each other (:class:`Value`).

A chunk is *resolved* once per run: its key (which resolves the upstream chunks its window
reads), then its stored entry, or compute, store and commit it under the entry's lock. An entry
stores the chunk's bundles and files and only the digests of its ``frames`` outputs: the frames
are handed to every stage reading them as they are computed (:class:`runner.broadcast.Broadcast`)
and computed again for a reader that asks after every registered reader passed them (or in a
later run). Reading a stored bundle hashes it against its entry's record; a damaged one is
reported and recomputed (:func:`runner.outputs.read_or_redo`). Frame chunks use the run through
:class:`RunServices` only: the run's :class:`runner.keys.Keys`, the cache store, progress
reporting and ``--jobs``.

Asking what a key or digest is and computing frames are separate calls: the ``known_*`` and
:meth:`FrameChunks.stored` methods answer from what is already stored (looking entries up,
never computing; None while an upstream stage still has to run: the scheduler asks them), the
others (:meth:`FrameChunks.key`, :meth:`FrameChunks.digests`, :meth:`FrameChunks.entry`)
resolve what they need, computing missing chunks. Both go through one description of what a
chunk's key reads (:meth:`FrameChunks.reads`), and compute keys and digests with
:mod:`runner.chunk_keys`, as the planner does.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from runner import notes
from runner.broadcast import Broadcast
from runner.bundle import PortType
from runner.cache import CacheStore, Entry
from runner.chunk_keys import chunk_key, port_digest, stream_digest, window_chunks
from runner.config import StageNode
from runner.depends import recording
from runner.digest import array_digest
from runner.errors import stage_errors
from runner.inputs import Inputs
from runner.keys import Keys
from runner.lifecycle import Lifecycle
from runner.outputs import check_frames, entry_context, load_bundle, read_or_redo, save_outputs
from runner.progress import Progress, Report
from runner.stage import FrameStage, StreamInfo
from runner.streams import ChunkedStream, ComputedStream, SharedStream, chunk_ranges
from runner.timing import own_time, waiting

if TYPE_CHECKING:
    from tqdm import tqdm


@dataclass(frozen=True)
class RunServices:
    """What frame chunks use of the run: its keys, the cache store, progress reporting, how
    many chunks are computed at once where a stage resolves its own chunks (``jobs``), the
    pipeline inputs (checked unchanged before an entry is committed), by how many producer
    threads for a stage whose readers stream it (``producers``), and whether a source's stream
    decodes its next chunk ahead on a thread of its own (``read_ahead``)."""

    keys: Keys
    store: CacheStore
    progress: Progress
    jobs: int
    inputs: Inputs
    producers: int = 1
    read_ahead: bool = True


@dataclass
class Value:
    """What one output (or pipeline input) gives downstream stages.

    Outputs of frame stages name their producer's :class:`FrameChunks` (``chunks``, ``port``),
    which gives digests per chunk as they are resolved, and the stream shape (``info``); other
    values carry their ``digest``.
    """

    type: PortType
    digest: str | None = None
    load: Callable[[], Any] | None = None
    chunks: FrameChunks | None = None
    port: str = ""
    info: StreamInfo | None = None
    _loaded: Any = field(default=None, repr=False)

    def known_digest(self) -> str | None:
        """The value's digest if it is known without computing anything; for a frame stage's
        output, once every chunk is stored; None until its producer runs."""
        if self.chunks is None:
            return self.digest
        return self.chunks.known_digest(self.port)

    def resolved_digest(self) -> str | None:
        """The value's digest; for a frame stage's output, the digest of all its chunks, which
        resolves them (computing the missing ones)."""
        if self.chunks is None:
            return self.digest
        return self.chunks.digest(self.port)

    def get(self, reader: str | None = None) -> Any:
        """The value; a frame stream as seen by stage ``reader`` (see :meth:`FrameChunks.stream`)."""
        if self.chunks is not None and self.type == "frames":
            return self.chunks.stream(self.port, reader)
        if self._loaded is None:
            self._loaded = self.load()
        return self._loaded


@dataclass(frozen=True)
class Read:
    """One upstream digest a chunk's key reads: the whole value at input ``port`` (``chunks``
    None), or the digests of its frame chunks ``lo..hi`` (``chunks = (lo, hi)``)."""

    port: str
    value: Value
    chunks: tuple[int, int] | None = None

    def known(self) -> str | list[str] | None:
        """The digest(s) if known without computing (see :meth:`Value.known_digest`), else None."""
        if self.chunks is None:
            return self.value.known_digest()
        return self.value.chunks.known_digests(self.value.port, *self.chunks)

    def resolved(self) -> str | list[str]:
        """The digest(s), resolving (computing) what is missing."""
        if self.chunks is None:
            return self.value.resolved_digest()
        return self.value.chunks.digests(self.value.port, *self.chunks)


def input_digests(inputs: dict[str, Value]) -> dict[str, str]:
    """Digest per input port, resolving frame streams."""
    return {port: v.resolved_digest() for port, v in inputs.items()}


class FrameChunks:
    """The chunks of one frame stage in one run, each resolved at most once.

    Resolving chunk ``i`` (:meth:`entry`) computes its key, which resolves the upstream chunks
    its window reads, then takes the stored entry or computes, stores and commits it under the
    entry's lock (a cached stage), logging a ``chunk`` event either way; the frames computed are
    offered to :attr:`broadcast` for the stages reading them. An uncached stage stores nothing:
    its chunks are computed whenever read (:meth:`stream`) and their digests derive from their
    keys. A *lazy* stage is resolved by its readers. Thread-safe: one lock per chunk.

    ``keep`` bounds the chunks computed ahead of the slowest registered reader
    (:class:`runner.broadcast.Broadcast`); ``lag`` is how many chunks behind the one it asks
    for a reader's position stays (a reader computing ``--jobs`` chunks at once asks out of
    order by up to ``2 * jobs`` chunks).

    What it uses of the run is ``run`` (:class:`RunServices`): keys, the store, progress.
    The stage's ``process`` is called through :attr:`life` (:class:`runner.lifecycle.Lifecycle`:
    opened before the first chunk computed, serialized for a ``"single"`` stage); the run
    calls :meth:`close_stage` at its end.
    ``entries`` (one per chunk, None until resolved) and :meth:`redo` serve publishing.
    """

    def __init__(
        self,
        run: RunServices,
        node: StageNode,
        stage: FrameStage,
        inputs: dict[str, Value],
        info: StreamInfo,
        *,
        forced: bool,
        lazy: bool,
        keep: int = 3,
    ):
        self.run, self.node, self.stage, self.inputs, self.info = run, node, stage, inputs, info
        self.life = Lifecycle(stage, device=run.keys.device)  # opened by the first chunk computed
        self.forced, self.lazy = forced, lazy
        at_once = max(run.jobs, run.producers)  # chunks of this stage's readers computed at once
        self.broadcast = Broadcast(keep=keep + 2 * (at_once - 1))
        self._lag = 2 * (at_once - 1)
        self.ranges = chunk_ranges(info.frames, run.keys.chunk_frames)
        self.keys: list[str | None] = [None] * len(self.ranges)
        self.entries: list[Entry | None] = [None] * len(self.ranges)
        self._cached = [False] * len(self.ranges)  # per chunk: found stored (not computed) in this run
        self.report = Report(node.name, node.uses, "cached", chunks=len(self.ranges), frames=info.frames)
        self._locks = [threading.Lock() for _ in self.ranges]
        self._book = threading.Lock()  # guards the report, the bar and the dicts below
        self._own_seconds = 0.0  # summed own time of the chunks computed under _busy
        self._intervals: list[tuple[float, float]] = []  # their wall intervals (perf_counter)
        self._upstream: dict[str, Any] | None = None
        self._streams: dict[str, ComputedStream] = {}
        self._readers: list[str] = []
        self._producer_threads: list[threading.Thread] = []  # every producer started (:meth:`produce`)
        self._bar: tqdm | None = None
        self._depends: set[Path] = set()  # files recorded by runner.depends while chunks were computed

    # -- keys and digests ------------------------------------------------------------------

    def reads(self, i: int) -> list[Read]:
        """What chunk ``i``'s key reads upstream: every input that is not a frame stream whole;
        of each frame stream, the chunks its window touches (:func:`runner.chunk_keys.window_chunks`)."""
        window, size = self.node.cls.window, self.run.keys.chunk_frames
        plain = [Read(port, v) for port, v in self.inputs.items() if v.type != "frames"]
        streams = [
            Read(port, v, window_chunks(self.ranges[i], window=window, frames=v.info.frames, chunk_frames=size))
            for port, v in self.inputs.items()
            if v.type == "frames"
        ]
        return plain + streams

    def _key_of(self, i: int, reads: list[Read], digests: list[str | list[str]]) -> str:
        """Cache key of chunk ``i`` given the digests of what it reads (:func:`runner.chunk_keys.chunk_key`)."""
        plain = {read.port: digest for read, digest in zip(reads, digests) if read.chunks is None}
        streams = {read.port: (read.value.info, digest) for read, digest in zip(reads, digests) if read.chunks is not None}
        return chunk_key(self.run.keys.material(self.node, plain), self.ranges[i], self.info, streams)

    def key(self, i: int) -> str:
        """Cache key of chunk ``i``, resolving the upstream chunks it reads."""
        if self.keys[i] is None:
            reads = self.reads(i)
            self.keys[i] = self._key_of(i, reads, [read.resolved() for read in reads])
        return self.keys[i]

    def known_key(self, i: int) -> str | None:
        """Cache key of chunk ``i`` if what it reads is known without computing, else None."""
        if self.keys[i] is None:
            reads, digests = self.reads(i), []
            for read in reads:
                digest = read.known()
                if digest is None:
                    return None
                digests.append(digest)
            self.keys[i] = self._key_of(i, reads, digests)
        return self.keys[i]

    def digests(self, port: str, lo: int, hi: int) -> list[str]:
        """Digests of output ``port`` in chunks ``lo..hi`` (inclusive), resolving them."""
        cached = self.node.cls.cached
        return [port_digest(port, self.entry(i) if cached else self.key(i)) for i in range(lo, hi + 1)]

    def known_digests(self, port: str, lo: int, hi: int) -> list[str] | None:
        """Digests of output ``port`` in chunks ``lo..hi`` if each is stored (or, uncached, its
        key is known), else None; computes nothing."""
        out = []
        for i in range(lo, hi + 1):
            chunk = self.stored(i) if self.node.cls.cached else self.known_key(i)
            if chunk is None:
                return None
            out.append(port_digest(port, chunk))
        return out

    def digest(self, port: str) -> str:
        """Digest of the whole output ``port`` (its chunk digests and the stream shape), resolving
        every chunk."""
        return stream_digest(self.digests(port, 0, len(self.ranges) - 1), self.info)

    def known_digest(self, port: str) -> str | None:
        """Digest of the whole output ``port`` if every chunk is stored, else None."""
        digests = self.known_digests(port, 0, len(self.ranges) - 1)
        return None if digests is None else stream_digest(digests, self.info)

    # -- resolving -------------------------------------------------------------------------

    def stored(self, i: int) -> Entry | None:
        """The entry of chunk ``i`` if it is stored (a cached stage, not forced): resolved
        without computing anything; None if it is missing or its key is not known until an
        upstream stage runs."""
        if self.entries[i] is None and not self.forced:
            with _holding(self._locks[i]):
                key = self.known_key(i) if self.entries[i] is None else None
                found = None if key is None else self.run.keys.lookup(self.node, key)
                if found is not None:
                    self._resolved(i, found, ran=False)
        return self.entries[i]

    def entry(self, i: int) -> Entry:
        """The stored entry of chunk ``i`` (cached stages), computed and committed if missing,
        once it lies within the broadcast's ``keep`` of the slowest reader
        (:meth:`runner.broadcast.Broadcast.wait_room`)."""
        self._passing(i)
        if self.entries[i] is None:
            if self.stored(i) is None:
                self.broadcast.wait_turn(i, lambda: self.entries[i] is not None)  # the producer's
                if self.entries[i] is None:
                    self.broadcast.wait_room(i)  # before taking a lock that a slower reader may need
            with _holding(self._locks[i]):
                if self.entries[i] is None:
                    key = self.key(i)
                    found = None if self.forced else self.run.keys.lookup(self.node, key)
                    ran = found is None
                    if ran:
                        found, ran = self._compute(i, key)
                    self._resolved(i, found, ran)
        return self.entries[i]

    def produce(self) -> None:
        """Compute the chunks in order on ``producers`` threads of their own (each takes the next
        chunk) while readers are registered with :attr:`broadcast`, unless such threads run
        already: the readers then only take the frames, none computes a chunk the others wait
        for while its own work (an encode) is pending."""
        claimed = iter(range(len(self.ranges)))
        threads = self.run.producers
        running = [threads]  # producers still running, under the lock that hands out the chunks
        claim = threading.Lock()
        producers = [
            threading.Thread(
                target=self._produce, args=(claimed, running, claim), name=f"produce-{self.node.name}-{k}", daemon=True
            )
            for k in range(threads)
        ]
        if not self.complete() and self.broadcast.produce(producers):
            self._producer_threads += producers
            for thread in producers:
                thread.start()

    def _produce(self, claimed: Iterator[int], running: list[int], claim: threading.Lock) -> None:
        """One producer thread: the next chunk not claimed yet, until none is left, or no reader."""
        self.run.progress.current = self.node.name
        try:
            while True:
                with claim:
                    i = next(claimed, None)
                if i is None or not self.broadcast.room_to_produce(i):
                    break
                self.entry(i)
        except BaseException:  # noqa: BLE001 - a reader then computes the chunk itself and raises the error (or the interrupt)
            self.broadcast.stop()
        with claim:
            running[0] -= 1
            if running[0] == 0:  # the last one: chunks left (no reader, or stopped) go to whoever asks
                self.broadcast.stop()

    def stop_producing(self) -> None:
        """Stop the producer threads (after the chunks they compute) and wait for every one
        started, also those a failed producer stopped already (:meth:`Broadcast.stop` hands
        them out once)."""
        self.broadcast.stop()
        for producer in self._producer_threads:
            if producer is not threading.current_thread():
                producer.join()

    def resolve_all(self) -> None:
        """Resolve every chunk now, ``--jobs`` at once."""
        for _ in map_ordered(self.entry, list(range(len(self.ranges))), jobs=self.run.jobs):
            pass

    def computed(self, i: int) -> bool:
        """True if chunk ``i`` was computed in this run (not found stored)."""
        with self._book:
            return self.entries[i] is not None and not self._cached[i]

    def complete(self) -> bool:
        return all(entry is not None for entry in self.entries)

    def _passing(self, i: int) -> None:
        """Tell the upstream stages chunk ``i`` reads that this stage is at chunk ``i``: it will
        ask them for no chunk before those it reads now."""
        for read in self.reads(i):
            if read.chunks is not None:
                read.value.chunks.passed(self.node.name, read.chunks[0])

    def passed(self, reader: str, chunk: int) -> None:
        """Stage ``reader`` asks for no chunk before ``chunk`` any more (:meth:`Broadcast.advance`)."""
        self.broadcast.advance(reader, chunk - self._lag)

    def _compute(self, i: int, key: str) -> tuple[Entry, bool]:
        """Compute chunk ``i`` under its entry's lock, unless another run stored it meanwhile;
        offer its frames to the readers."""
        store, keys, node = self.run.store, self.run.keys, self.node
        start, stop = self.ranges[i]
        with store.locked(key, on_wait=self.run.progress.waiting(node)):
            entry = None if self.forced else keys.lookup(node, key)
            if entry is not None:
                return entry, False
            timing = self._busy() if self.lazy else contextlib.nullcontext()
            with timing, store.writing(key) as tmp:
                with stage_errors(node):
                    with recording(set()) as files, notes.recording() as warned:
                        upstream, params = self._inputs(), dict(node.params)
                        ctx = entry_context(tmp, device=keys.device, progress=lambda n: None)
                        result = self.life.call(upstream, params, lambda: self.stage.process(start, stop, upstream, params, ctx))
                    record = save_outputs(node.cls.outputs, result, tmp, frames=(stop - start, self.info))
                with self._book:  # a stage may read such a file once, for all its chunks
                    self._depends |= files
                    files = set(self._depends)
                with stage_errors(node):
                    self.run.inputs.check(node.name)
                entry = store.commit(
                    key,
                    tmp,
                    {
                        "stage": node.name,
                        "uses": node.uses,
                        "range": [start, stop],
                        **record,
                        "depends": keys.depends(files),
                        "warnings": warned,
                    },
                    replace=self.forced,
                )
        self.broadcast.offer(i, {port: np.asarray(result[port]) for port in self._frame_ports()})
        return entry, True

    def redo(self, i: int) -> Entry:
        """Recompute chunk ``i``, whose stored entry was found damaged; the new entry."""
        with _holding(self._locks[i]):
            damaged = self.entries[i]
            if damaged is not None:
                self.run.store.discard(damaged)
                self.entries[i] = None
                with self._book:
                    self.report.chunks_cached -= self._cached[i]
        return self.entry(i)

    def _resolved(self, i: int, entry: Entry, ran: bool) -> None:
        progress = self.run.progress
        with self._book:
            self.entries[i] = entry
            self._cached[i] = not ran
            self.report.chunks_cached += not ran
            start, stop = self.ranges[i]
            progress.log(
                {"event": "chunk", "stage": self.node.name, "start": start, "stop": stop, "status": "ran" if ran else "cached"}
            )
            if not ran:
                progress.replay(self.node.name, entry.record)
            if self._bar is None:
                self._bar = progress.bar(self.node, self.info.frames)
            self._bar.update(stop - start)
            if ran and self.lazy:
                self._readers += [
                    reader
                    for reader in dict.fromkeys([progress.current, *self.broadcast.readers()])
                    if reader not in (None, self.node.name, *self._readers)
                ]
        self.broadcast.resolved()
        self.run.store.touch(entry)

    @contextlib.contextmanager
    def _busy(self) -> Iterator[None]:
        """Time one chunk computed by this stage on whichever thread (:func:`own_time`): its own
        seconds and CPU seconds are summed, and the wall interval kept (:meth:`finish`)."""
        started = time.perf_counter()
        with own_time(self._spent):
            yield
        with self._book:
            self._intervals.append((started, time.perf_counter()))

    def _spent(self, seconds: float, cpu_seconds: float) -> None:
        with self._book:
            self._own_seconds += seconds
            self.report.cpu_seconds += cpu_seconds

    def _seconds(self) -> float:
        """The stage's seconds: the sum of its chunks' own times, but no more than the wall time
        during which one of its chunks was computing (several threads computing its chunks at
        once)."""
        busy, end = 0.0, float("-inf")
        for start, stop in sorted(self._intervals):
            busy += max(0.0, stop - max(start, end))
            end = max(end, stop)
        return min(self._own_seconds, busy)

    def _inputs(self) -> dict[str, Any]:
        """What ``process`` is handed: frame streams, loaded bundles, paths (loaded once)."""
        if self._upstream is None:
            self._upstream = {port: v.get(self.node.name) for port, v in self.inputs.items()}
        return self._upstream

    def finish(self) -> Report:
        """The stage's report once every chunk is resolved; remembers its key material."""
        report, count = self.report, len(self.ranges)
        report.seconds = self._seconds()
        report.status = "cached" if report.chunks_cached == count else "ran" if report.chunks_cached == 0 else "partial"
        if self._readers:
            report.reason = f"computed while {', '.join(self._readers)} read it"
        self.close()
        self.run.keys.remember(self.node, self.run.keys.material(self.node, input_digests(self.inputs)))
        return report

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()

    def close_stage(self) -> None:
        """Close the stage (:meth:`runner.stage.Stage.close`) once nothing computes its chunks
        any more: the run's stage threads and producers have ended; its streams' read-ahead
        threads are stopped here."""
        for stream in self._streams.values():
            stream.stop()
        self.life.close()

    # -- outputs ---------------------------------------------------------------------------

    def stream(self, port: str, reader: str | None = None) -> ChunkedStream:
        """Frames of output ``port`` as stage ``reader`` reads them: of a cached stage, each
        chunk resolved (computed and its entry committed, if missing) when first asked for and
        handed over as computed, or computed again if no registered reader kept it; of an
        uncached stage, chunks computed as read."""
        if self.node.cls.cached:
            return SharedStream(
                self.info,
                self.ranges,
                lambda i, lo, hi: self._frames(i, port, lo, hi),
                lambda i: None if reader is None else self.passed(reader, i),
            )
        with self._book:
            if port not in self._streams:
                self._streams[port] = ComputedStream(
                    self.info,
                    self.ranges,
                    lambda i, p=port: self._process(*self.ranges[i])[p],
                    keep=self.run.jobs + 2,
                    read_ahead=self.run.read_ahead and is_source(self.node.cls),
                )
            return self._streams[port]

    def _frame_ports(self) -> list[str]:
        return [port for port, kind in self.node.cls.outputs.items() if kind == "frames"]

    def _frames(self, i: int, port: str, lo: int, hi: int) -> np.ndarray:
        """Frames ``[lo, hi)`` (from the chunk's first) of output ``port`` in chunk ``i`` of a
        cached stage: as computed when its entry was resolved, or computed again if no
        registered reader kept them: the whole chunk, offered to the other readers, or, for a
        part of it, just those frames (a reader picking frames here and there)."""
        self.entry(i)
        frames = self.broadcast.take(i, port)
        if frames is not None:
            return frames[lo:hi]
        start, stop = self.ranges[i]
        if hi - lo < stop - start:
            return self._process(start + lo, start + hi)[port]
        self.broadcast.wait_room(i)  # before taking a lock that a slower reader may need
        computed = None
        with _holding(self._locks[i]):
            frames = self.broadcast.take(i, port)
            if frames is None:
                computed = self._process(start, stop)
                self.broadcast.offer(i, computed)
                frames = computed[port]
        if computed is not None:  # hashed outside the lock: the other readers take the frames meanwhile
            self._check_recomputed(i, computed)
        return frames

    def _read(self, i: int, read: Callable[[Entry], Any]) -> Any:
        """``read`` of chunk ``i``'s entry, recomputing the chunk if it is damaged."""
        return read_or_redo(
            read, self.entries[i], redo=lambda: self.redo(i), on_damaged=lambda exc: self.run.progress.damaged(self.node, exc)
        )

    def load(self, port: str) -> dict[str, np.ndarray]:
        """A bundle output, its chunks concatenated, once every chunk is resolved."""
        self.resolve_all()
        parts = [self._read(i, lambda entry: load_bundle(entry, port)) for i in range(len(self.ranges))]
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}

    def _check_recomputed(self, i: int, computed: dict[str, np.ndarray]) -> None:
        """Compare chunk ``i``'s frames computed again with the digests its entry recorded when
        they were first computed: the stages downstream were keyed on those digests, so a stage
        that does not compute the same frames twice (threads, a GPU, an unseeded random number)
        makes a resumed run's outputs differ from an uninterrupted run's. Reported, not fatal
        (a ``nondeterministic`` event and one warning line per stage)."""
        recorded = self.entries[i].record.get("outputs", {})
        differ = [
            port for port, frames in computed.items() if port in recorded and array_digest(frames) != recorded[port]["digest"]
        ]
        if differ:
            start, stop = self.ranges[i]
            self.run.progress.nondeterministic(self.node, start, stop, differ)

    def _process(self, start: int, stop: int) -> dict[str, np.ndarray]:
        """The ``frames`` outputs ``(stop - start, H, W, C)`` of frames ``[start, stop)``
        computed without storing anything (an uncached stage's chunk, or a cached stage's frames
        needed again: a ``recompute`` event); the stage's ``files`` outputs, if any, are written
        to a folder dropped at once."""
        timing = self._busy() if self.node.cls.cached else contextlib.nullcontext()
        if self.node.cls.cached:
            self.run.progress.log({"event": "recompute", "stage": self.node.name, "start": start, "stop": stop})
        with timing, self.run.store.writing(f"again-{self.node.name}") as tmp, stage_errors(self.node):
            ctx = entry_context(tmp, device=self.run.keys.device, progress=lambda n: None)
            ctx.log = logging.getLogger(f"runner.stage.{self.node.name}")
            upstream, params = self._inputs(), dict(self.node.params)
            result = self.life.call(upstream, params, lambda: self.stage.process(start, stop, upstream, params, ctx))
            frames = {port: np.asarray(result[port]) for port in self._frame_ports()}
            for port, array in frames.items():
                check_frames(port, array, stop - start, self.info)
        return frames


@contextlib.contextmanager
def _holding(lock: threading.Lock) -> Iterator[None]:
    """Hold ``lock``; the time spent getting it (another thread computing the chunk under it)
    is waiting (:func:`runner.timing.waiting`), not the caller's own time."""
    with waiting():
        lock.acquire()
    try:
        yield
    finally:
        lock.release()


def is_source(cls: type) -> bool:
    """True for an uncached frame stage that reads no frames (``video.decode``): its chunks are
    computed as read and depend on nothing another thread drives (read-ahead, runner.offload)."""
    return issubclass(cls, FrameStage) and not cls.cached and "frames" not in cls.inputs.values()


def map_ordered(fn: Callable[[int], Any], items: list[int], *, jobs: int) -> Iterator[tuple[int, Any]]:
    """Yield ``(item, fn(item))``; with ``jobs > 1`` up to ``jobs`` calls run in threads, at
    most ``2 * jobs`` submitted ahead (bounded memory). The first exception cancels the rest."""
    if jobs <= 1:
        for item in items:
            yield item, fn(item)
        return
    pool = ThreadPoolExecutor(max_workers=jobs)
    pending: dict[Future[Any], int] = {}
    queue = list(items)
    try:
        while queue or pending:
            while queue and len(pending) < 2 * jobs:
                item = queue.pop(0)
                pending[pool.submit(fn, item)] = item
            done, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                item = pending.pop(future)
                yield item, future.result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
