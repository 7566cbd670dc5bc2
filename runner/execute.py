"""Scheduling: run (or, for ``--dry-run``, plan) a validated pipeline against the cache.

Stages are visited one after the other in topological order. A sequence stage is one cache
entry. A frame stage is one entry per chunk of ``chunk_frames`` frames, and a
:class:`FrameChunks` *resolves* each chunk once: its key (which resolves the upstream chunks its
window reads), then the stored entry, or compute, store and commit it under the entry's lock. So
an interrupted run recomputes only the chunks it had not finished.

When a chunk is resolved depends on who reads the stage:

- a cached frame stage that other stages read (with ``--jobs 1`` and no ``--force``) is
  resolved *lazily*: each chunk is computed and stored when a downstream stage first needs it,
  then read back (from the page cache), so decode -> gray -> write.video streams chunk by
  chunk and the encoder's threads overlap the Python work; a second reader reads the stored
  chunks;
- any other cached frame stage (no reader, ``--force``, ``--jobs N``) resolves all its chunks
  at its turn, with ``--jobs`` threads;
- a frame stage declaring ``cached = False`` (decoding) is never stored: its chunks are computed
  whenever they are read, and identified by their cache key instead of their bytes.

Every key (see :mod:`runner.digest`) includes the digests of the inputs actually used: a frame
stage's chunk depends on the upstream chunks its window overlaps, a sequence stage on the whole
upstream output. So a stage whose upstream re-ran but produced identical bytes is a cache hit.
A sequence stage reading a stream still being computed cannot know its key before the stream
is whole: it then either runs while the stream is computed (its key is taken at the end and
its entry committed, the first commit winning), or, when the first chunk computed now equals
what it read in its last completed run (the upstream's bytes are probably unchanged), waits for
the whole stream and looks its entry up first. See :meth:`Runner._read_while_computed`.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import importlib.metadata
import json
import logging
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from runner.cache import CacheStore, Entry
from runner.config import ConfigError, Issue, Pipeline, StageNode, Where
from runner.depends import recording
from runner.digest import cache_key, combine, file_digest, input_digest, library_versions
from runner.outputs import Damaged, check_frames, load_bundle, load_frames, load_mapped, save_outputs, verify_files
from runner.publish import Published, conflicts, publish, remove_leftovers
from runner.stage import Context, FrameStage, StageError, StreamInfo
from runner.streams import ChunkedStream, ComputedStream, StoredStream, chunk_ranges

if TYPE_CHECKING:
    from tqdm import tqdm

# Part of every key: entries stored by an older layout of the cache (no sha256 per data file)
# are never looked up.
CACHE_FORMAT = 2


class StageFailed(Exception):
    """A stage raised :class:`StageError`; the message names the stage."""

    def __init__(self, node: StageNode, error: StageError):
        self.node = node
        super().__init__(f"stage {node.name!r} ({node.uses}): {error}")


@dataclass
class Options:
    cache: CacheStore
    device: str = "cpu"
    jobs: int = 1
    force: frozenset[str] = frozenset()
    until: str | None = None
    dry_run: bool = False
    out: Path | None = None
    progress: bool = False
    log: Callable[[dict[str, Any]], None] = lambda event: None
    echo: Callable[[str], None] = lambda line: None
    warn: Callable[[str], None] = lambda line: None  # one line on stderr (a damaged cache entry)


@dataclass
class Value:
    """What one output (or pipeline input) gives downstream stages.

    Outputs of frame stages name their producer's :class:`FrameChunks` (``chunks``, ``port``),
    which gives digests per chunk as they are resolved, and the stream shape (``info``); other
    values carry their ``digest``, None in a dry run when the producer has not run yet.
    """

    type: str
    digest: str | None = None
    load: Callable[[], Any] | None = None
    chunks: FrameChunks | None = None
    port: str = ""
    info: StreamInfo | None = None
    _loaded: Any = field(default=None, repr=False)

    def resolved_digest(self, *, compute: bool = True) -> str | None:
        """The value's digest; for a frame stage's output, the digest of all its chunks, which
        resolves them (computing the missing ones), or None if ``compute`` is False and some
        chunk is not stored yet."""
        if self.chunks is None:
            return self.digest
        return self.chunks.digest(self.port, compute=compute)

    def get(self) -> Any:
        if self.chunks is not None and self.type == "frames":
            return self.chunks.stream(self.port)
        if self._loaded is None:
            self._loaded = self.load()
        return self._loaded


@dataclass
class Report:
    """One stage's outcome: ``status`` is cached / ran / partial / on demand (run) or
    cached / will run / may run / on demand (dry run)."""

    stage: str
    uses: str
    status: str
    reason: str = ""
    chunks: int | None = None
    chunks_cached: int = 0
    frames: int | None = None
    seconds: float = 0.0

    def line(self) -> str:
        parts = [f"{self.stage:<14} {self.uses:<18} {self.status:<9}"]
        if self.chunks is not None:
            parts.append(f"{self.chunks_cached}/{self.chunks} chunks cached")
        if self.frames is not None:
            parts.append(f"{self.frames} frames")
        if self.status in ("cached", "ran", "partial"):
            parts.append(f"{self.seconds:.2f} s")
        if self.reason:
            parts.append(f"({self.reason})")
        return "  ".join(parts)


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


_clock = threading.local()


@contextlib.contextmanager
def _own_time(add: Callable[[float], None]) -> Iterator[None]:
    """Time the block and pass ``add`` its wall seconds minus those of timed blocks nested in
    it on this thread (chunks of an upstream stage computed while this one reads them), so
    that each stage's summary counts its own time only."""
    outer = getattr(_clock, "nested", 0.0)
    _clock.nested = 0.0
    started = time.perf_counter()
    try:
        yield
    finally:
        elapsed = time.perf_counter() - started
        add(elapsed - _clock.nested)
        _clock.nested = outer + elapsed


class Runner:
    """Runs one pipeline with bound inputs; :meth:`run` returns one :class:`Report` per stage."""

    def __init__(self, pipeline: Pipeline, bound: dict[str, Path], options: Options):
        self.pipeline = pipeline
        self.opts = options
        self.store = options.cache
        self.values: dict[tuple[str | None, str], Value] = {}
        for name, path in bound.items():
            kind = pipeline.inputs[name].type
            self.values[(None, name)] = Value(kind, input_digest(kind, path), load=lambda p=path: Path(p))
        self.entries: dict[str, list[Entry]] = {}  # per stage, its entries (one per chunk of a frame stage)
        self.redo: dict[str, Callable[[int], Entry]] = {}  # per stage, recompute its entry i (found damaged)
        self._file_digests: dict[Path, str | None] = {}  # files recorded by runner.depends, hashed this run
        self._stale: dict[str, str] = {}  # per stage, why a stored entry was stale (dry-run reason)
        self.memo_dir = self.store.root / "runs"
        self.current: str | None = None  # the stage whose turn it is
        self._lazy: list[FrameChunks] = []  # lazy frame stages not reported yet

    def selected(self) -> list[StageNode]:
        names = self.pipeline.ancestors(self.opts.until) if self.opts.until else set(self.pipeline.stages)
        return [node for name, node in self.pipeline.stages.items() if name in names]

    def run(self) -> list[Report]:
        """Run (or plan) every selected stage, then publish.

        Raises
        ------
        ConfigError
            ``--out`` holds something at a stage's folder that no earlier publish wrote
            (checked before anything runs).
        StageFailed
            A stage failed, or writing the cache or ``--out`` failed (disk full: the message
            names the stage and the file).
        """
        publishing = [node for node in self.selected() if "files" in node.cls.outputs.values()]
        if not self.opts.dry_run and self.opts.out is not None:
            problems = conflicts(self.opts.out, [node.name for node in publishing])
            if problems:
                raise ConfigError([Issue(Where("--out"), str(self.opts.out), p) for p in problems])
            remove_leftovers(self.opts.out)
        reports: list[Report] = []

        def emit(report: Report) -> None:
            self.opts.log({"event": "stage", **asdict(report)})
            self.opts.echo(report.line())
            reports.append(report)

        try:
            for node in self.selected():
                self.current = node.name
                self.opts.log({"event": "stage_start", "stage": node.name, "uses": node.uses})
                spent: list[float] = []
                with _own_time(spent.append), _stage_errors(node):
                    if issubclass(node.cls, FrameStage):
                        report = self._frame_stage(node)
                    else:
                        report = self._sequence_stage(node)
                for finished in self._finished_lazy():
                    emit(finished)
                if report is not None:  # None: a lazy frame stage, reported once resolved
                    report.seconds += spent[0]
                    emit(report)
            self.current = None
            for chunks in self._lazy:  # chunks no reader needed (normally none)
                chunks.resolve_all()
            for finished in self._finished_lazy():
                emit(finished)
        finally:
            for chunks in self._lazy:
                chunks.close()
        if not self.opts.dry_run and self.opts.out is not None:
            for node in publishing:
                ports = [p for p, kind in node.cls.outputs.items() if kind == "files"]
                if self.entries.get(node.name):
                    item = Published(node.name, node.uses, ports, self.entries[node.name], self.redo[node.name])
                    with _stage_errors(node):
                        publish(self.opts.out, item, on_damaged=lambda exc, n=node: self.damaged(n, exc))
        return reports

    def damaged(self, node: StageNode, exc: Damaged) -> None:
        """Report a damaged cache file (one line on stderr, a ``damaged`` event); the caller
        recomputes its entry."""
        self.opts.warn(f"warning: stage {node.name!r}: damaged cache entry ({exc}); recomputing it")
        self.opts.log({"event": "damaged", "stage": node.name, "file": str(exc.path)})

    def read_stored(self, node: StageNode, index: int, read: Callable[[Entry], Any]) -> Any:
        """``read(entry)`` of the stage's entry ``index``; if that raises :class:`Damaged`, the
        entry is reported, recomputed and read again."""
        try:
            return read(self.entries[node.name][index])
        except Damaged as exc:
            self.damaged(node, exc)
        try:
            return read(self.redo[node.name](index))
        except Damaged as exc:
            raise StageFailed(node, StageError(f"cache entry damaged again right after it was computed: {exc}")) from None

    def _finished_lazy(self) -> list[Report]:
        """Reports of the lazy frame stages whose chunks are now all resolved."""
        done = [chunks for chunks in self._lazy if chunks.complete()]
        self._lazy = [chunks for chunks in self._lazy if chunks not in done]
        return [chunks.finish() for chunks in done]

    # -- keys ------------------------------------------------------------------------------

    def _inputs(self, node: StageNode) -> dict[str, Value]:
        return {port: self.values[(ref.stage, ref.port)] for port, ref in node.inputs.items()}

    @staticmethod
    def _digests(inputs: dict[str, Value], *, compute: bool = True) -> dict[str, str] | None:
        """Digest per input port (resolving frame streams); None if ``compute`` is False and
        one is not known without computing."""
        digests = {port: v.resolved_digest(compute=compute) for port, v in inputs.items()}
        return None if None in digests.values() else digests

    def _material(self, node: StageNode, digests: dict[str, str]) -> dict[str, Any]:
        schema = {p.name: p for p in node.cls.params}
        material = {
            "cache_format": CACHE_FORMAT,
            "stage": node.uses,
            "version": node.cls.version,
            "params": {k: v for k, v in node.params.items() if k not in schema or schema[k].in_key},
            "inputs": digests,
            "device": self.opts.device,
            "libs": library_versions(),
        }
        files = {k: file_digest(Path(v)) for k, v in node.params.items()
                 if k in schema and schema[k].file and isinstance(v, str) and Path(v).is_file()}
        if files:
            material["param_files"] = files
        if issubclass(node.cls, FrameStage):
            material["chunk_frames"] = self.pipeline.chunk_frames
        return material

    def _unknown(self, node: StageNode) -> list[str | None]:
        """Dry run: the upstream stages whose outputs are not known (they will run)."""
        return [ref.stage for ref in node.inputs.values()
                if self.values[(ref.stage, ref.port)].resolved_digest(compute=False) is None]

    def _memo_path(self, node: StageNode) -> Path:
        ident = f"{self.pipeline.path.resolve()}\n{node.name}"
        return self.memo_dir / f"{hashlib.sha256(ident.encode()).hexdigest()[:32]}.json"

    def _memo(self, node: StageNode) -> dict[str, Any] | None:
        try:
            return json.loads(self._memo_path(node).read_text())
        except (OSError, ValueError):
            return None

    def _remember(self, node: StageNode, material: dict[str, Any]) -> None:
        """Keep the key material of this stage's last completed run, to explain dry runs."""
        self.memo_dir.mkdir(parents=True, exist_ok=True)
        path = self._memo_path(node)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(material, sort_keys=True))
        os.replace(tmp, path)

    def lookup(self, node: StageNode, key: str) -> Entry | None:
        """The complete entry for ``key`` if the files it recorded (:mod:`runner.depends`)
        are unchanged; a stale entry is removed (kept in a dry run) and None returned."""
        entry = self.store.lookup(key)
        if entry is None:
            return None
        recorded = entry.record.get("depends", {})
        changed = [path for path, sha256 in recorded.items() if self._file_sha256(Path(path)) != sha256]
        if not changed:
            return entry
        self._stale[node.name] = f"file {changed[0]} changed"
        if not self.opts.dry_run:
            self.store.discard(entry)
        return None

    def depends_digests(self, files: set[Path]) -> dict[str, str | None]:
        """``{path: sha256}`` of the files a computation recorded (None: missing)."""
        return {str(path): self._file_sha256(path) for path in sorted(files)}

    def _file_sha256(self, path: Path) -> str | None:
        """sha256 of a recorded file, hashed once per run."""
        if path not in self._file_digests:
            try:
                self._file_digests[path] = file_digest(path)
            except OSError:
                self._file_digests[path] = None
        return self._file_digests[path]

    def _why(self, node: StageNode, material: dict[str, Any]) -> str:
        if node.name in self._stale:
            return self._stale[node.name]
        old = self._memo(node)
        if old is None:
            return "never run with this configuration"
        changes = []
        if (old.get("stage"), old.get("version")) != (material["stage"], material["version"]):
            changes.append(f"stage {old.get('stage')} {old.get('version')} -> {material['stage']} {material['version']}")
        old_params, new_params = old.get("params", {}), material["params"]
        for name in sorted(set(old_params) | set(new_params)):
            if old_params.get(name) != new_params.get(name):
                changes.append(f"param {name}: {old_params.get(name)!r} -> {new_params.get(name)!r}")
        old_files, new_files = old.get("param_files", {}), material.get("param_files", {})
        for name in sorted(set(old_files) | set(new_files)):
            if old_files.get(name) != new_files.get(name) and name in new_params and old_params.get(name) == new_params[name]:
                changes.append(f"file of param {name} changed: {new_params[name]}")
        for port in sorted(set(old.get("inputs", {})) | set(material["inputs"])):
            if old.get("inputs", {}).get(port) != material["inputs"].get(port):
                changes.append(f"input {port} changed")
        libs = [n for n in sorted(material["libs"]) if old.get("libs", {}).get(n) != material["libs"][n]]
        if libs:
            changes.append(f"library versions changed: {', '.join(libs)}")
        if old.get("device") != material["device"]:
            changes.append(f"device {old.get('device')} -> {material['device']}")
        if old.get("chunk_frames", material.get("chunk_frames")) != material.get("chunk_frames"):
            changes.append(f"chunk_frames {old.get('chunk_frames')} -> {material.get('chunk_frames')}")
        return "; ".join(changes) or "cache entry missing (cleared or collected)"

    # -- sequence stages -------------------------------------------------------------------

    def _sequence_stage(self, node: StageNode) -> Report:
        inputs = self._inputs(node)
        forced = node.name in self.opts.force
        if self.opts.dry_run:
            unknown = self._unknown(node)
            if unknown:
                self._set_unknown(node)
                return Report(node.name, node.uses, "may run", _after(unknown))
            material = self._material(node, self._digests(inputs))
            entry = None if forced else self.lookup(node, cache_key(material))
            if entry is None:
                self._set_unknown(node)
                return Report(node.name, node.uses, "will run", "forced (--force)" if forced else self._why(node, material))
            self._set_outputs(node, entry, inputs)
            return Report(node.name, node.uses, "cached", "cache hit")
        report = Report(node.name, node.uses, "cached")
        pending = {port: v for port, v in inputs.items() if v.resolved_digest(compute=False) is None}
        streaming = bool(pending) and (forced or self._read_while_computed(node, pending))
        key = None if streaming else cache_key(self._material(node, self._digests(inputs)))
        entry = None if forced or key is None else self.lookup(node, key)
        if entry is None:
            entry, ran = self._run_sequence(node, inputs, key, forced)
            report.status = "ran" if ran else "cached"
        if streaming:
            names = ", ".join(dict.fromkeys(node.inputs[port].stage for port in pending))
            report.reason = f"read {names} while it was computed"
        self.store.touch(entry)
        streams = {port: v.chunks.digests(v.port, 0, len(v.chunks.ranges) - 1)
                   for port, v in inputs.items() if v.chunks is not None and v.type == "frames"}
        self._remember(node, {**self._material(node, self._digests(inputs)), "input_chunks": streams})
        self._set_outputs(node, entry, inputs)
        return report

    def _read_while_computed(self, node: StageNode, pending: dict[str, Value]) -> bool:
        """Whether sequence stage ``node`` runs while its ``pending`` inputs (streams not all
        stored yet) are computed, instead of after them.

        Its key needs their whole digests, so running first means running even when its entry
        exists (an upstream stage re-ran and produced identical bytes). Hence: compute the
        first missing chunk of each pending stream now and compare it with the same chunk in
        the stage's last completed run; run while computed if one differs (the key changes),
        else resolve everything first and look the entry up.
        """
        read = (self._memo(node) or {}).get("input_chunks", {})
        for port, v in pending.items():
            if v.type != "frames":
                continue
            count = len(v.chunks.ranges)
            first = next((i for i in range(count) if v.chunks.digests(v.port, i, i, compute=False) is None), None)
            if first is not None and read.get(port, [])[first:first + 1] != v.chunks.digests(v.port, first, first):
                return True
        return False

    def _run_sequence(self, node: StageNode, inputs: dict[str, Value], key: str | None,
                      forced: bool) -> tuple[Entry, bool]:
        """Run a sequence stage under its entry's lock and commit its entry; with ``key`` None
        (inputs computed while read) the key is taken after the run, and the first commit of
        that key wins. Returns the entry and whether this run computed it."""
        frames = next((v.info.frames for v in inputs.values() if v.info is not None), None)
        lock = contextlib.nullcontext() if key is None else self.store.locked(key, on_wait=self._waiting(node))
        with self._bar(node, frames) as bar, lock:
            entry = None if forced or key is None else self.lookup(node, key)
            if entry is not None:
                return entry, False
            with self.store.writing(key or f"pending-{node.name}") as tmp:
                values = {port: v.get() for port, v in inputs.items()}
                with recording(set()) as files:
                    result = node.cls().run(values, dict(node.params), self._context(tmp, bar.update))
                record = save_outputs(node.cls.outputs, result, tmp, frames=None)
                if key is None:
                    key = cache_key(self._material(node, self._digests(inputs)))
                return self.store.commit(key, tmp, {"stage": node.name, "uses": node.uses, **record,
                                                    "depends": self.depends_digests(files)}, replace=forced), True

    # -- frame stages ----------------------------------------------------------------------

    def _frame_stage(self, node: StageNode) -> Report | None:
        inputs = self._inputs(node)
        forced = node.name in self.opts.force
        unknown = self._unknown(node) if self.opts.dry_run else []
        if unknown:
            self._set_unknown(node)
            return Report(node.name, node.uses, "may run", _after(unknown))
        stage = node.cls()
        info = self._stream_info(node, stage, inputs)
        lazy = (node.cls.cached and not self.opts.dry_run and not forced and self.opts.jobs == 1
                and self._is_read(node))
        chunks = FrameChunks(self, node, stage, inputs, info, forced=forced, lazy=lazy)
        for port, kind in node.cls.outputs.items():
            load = None if kind == "frames" else (lambda p=port: chunks.load(p))
            self.values[(node.name, port)] = Value(kind, load=load, chunks=chunks, port=port, info=info)
        if not node.cls.cached:
            return Report(node.name, node.uses, "on demand", "computed while downstream stages read it",
                          frames=info.frames)
        if self.opts.dry_run:
            report = chunks.report
            count = len(chunks.ranges)
            if sum(chunks.entry(i, compute=False) is not None for i in range(count)) == count:
                report.reason = "cache hit"
                return report
            self._set_unknown(node)
            report.status = "will run"
            if forced:
                report.reason = "forced (--force)"
            elif report.chunks_cached:
                report.reason = f"{count - report.chunks_cached} of {count} chunks missing (earlier run incomplete)"
            else:
                report.reason = self._why(node, self._material(node, self._digests(inputs)))
            return report
        if lazy:
            self._lazy.append(chunks)
            return None
        chunks.resolve_all()
        return chunks.finish()

    def _is_read(self, node: StageNode) -> bool:
        """True if a selected stage reads one of ``node``'s outputs."""
        return any(ref.stage == node.name for other in self.selected() for ref in other.inputs.values())

    def _stream_info(self, node: StageNode, stage: FrameStage, inputs: dict[str, Value]) -> StreamInfo:
        """The stage's output stream shape; cached when the stage computes it itself (probing
        a video), taken from the frames input otherwise."""
        if not _defines_stream_info(node.cls):
            return next(v.info for port, v in inputs.items() if node.cls.inputs[port] == "frames")
        key = cache_key({**self._material(node, self._digests(inputs)), "stream_info": True})
        entry = self.store.lookup(key)
        if entry is None:
            info = stage.stream_info({port: v.get() for port, v in inputs.items()}, dict(node.params))
            if self.opts.dry_run:
                return info
            with self.store.writing(key) as tmp:
                entry = self.store.commit(key, tmp, {"stage": node.name, "uses": node.uses, "info": asdict(info)})
        return StreamInfo(**entry.record["info"])

    def _chunk_inputs(self, node: StageNode, inputs: dict[str, Value], start: int, stop: int, *,
                      compute: bool) -> dict[str, Any] | None:
        """Digests of the upstream frame chunks that frames ``[start - window, stop + window)``
        touch (clamped to the clip), resolving them; None if ``compute`` is False and one is
        not stored yet. A stage that defines its own stream shape may map output frames to any
        input frames, so each of its chunks depends on whole input streams."""
        own_shape = _defines_stream_info(node.cls)
        used = {}
        for port, v in inputs.items():
            if v.type != "frames":
                continue
            if own_shape:
                digest = v.resolved_digest(compute=compute)
                if digest is None:
                    return None
                used[port] = {"info": asdict(v.info), "stream": digest}
                continue
            size, window = self.pipeline.chunk_frames, node.cls.window
            lo = max(0, start - window) // size
            hi = (min(v.info.frames, stop + window) - 1) // size
            digests = v.chunks.digests(v.port, lo, hi, compute=compute)
            if digests is None:
                return None
            used[port] = {"info": asdict(v.info), "chunks": digests}
        return used

    # -- outputs ---------------------------------------------------------------------------

    def _set_unknown(self, node: StageNode) -> None:
        for port, kind in node.cls.outputs.items():
            self.values[(node.name, port)] = Value(kind, None)

    def _set_outputs(self, node: StageNode, entry: Entry, inputs: dict[str, Value]) -> None:
        """Hand a sequence stage's stored outputs to downstream stages (read, verified, when
        first needed; a damaged entry is recomputed from ``inputs``)."""
        self.entries[node.name] = [entry]

        def redo(index: int) -> Entry:
            self.store.discard(self.entries[node.name][index])
            with _stage_errors(node):
                self.entries[node.name][index] = self._run_sequence(node, inputs, entry.key, forced=False)[0]
            return self.entries[node.name][index]

        self.redo[node.name] = redo
        for port, kind in node.cls.outputs.items():
            read = (lambda e, p=port: verify_files(e, p)) if kind == "files" else (lambda e, p=port: load_bundle(e, p))
            self.values[(node.name, port)] = Value(kind, entry.record["outputs"][port]["digest"],
                                                   lambda r=read: self.read_stored(node, 0, r))

    # -- helpers ---------------------------------------------------------------------------

    def _context(self, tmp: Path, progress: Callable[[int], None]) -> Context:
        def files_dir(port: str) -> Path:
            folder = tmp / "files" / port
            folder.mkdir(parents=True, exist_ok=True)
            return folder

        return Context(device=self.opts.device, files_dir=files_dir, progress=progress)

    def _bar(self, node: StageNode, total: int | None) -> tqdm:
        from tqdm import tqdm  # here: importing it costs start-up time

        return tqdm(total=total, desc=node.name, unit="frame", file=sys.stderr, leave=False,
                    disable=not self.opts.progress, dynamic_ncols=True)

    def _waiting(self, node: StageNode) -> Callable[[dict[str, Any]], None]:
        def on_wait(holder: dict[str, Any]) -> None:
            self.opts.log({"event": "wait", "stage": node.name, "holder_pid": holder.get("pid")})

        return on_wait


class FrameChunks:
    """The chunks of one frame stage in one run, each resolved at most once.

    Resolving chunk ``i`` (:meth:`entry`) computes its key, which resolves the upstream chunks
    its window reads, then takes the stored entry or computes, stores and commits it under the
    entry's lock (a cached stage), logging a ``chunk`` event either way. An uncached stage
    stores nothing: its chunks are computed whenever read (:meth:`stream`) and their digests
    derive from their keys. A *lazy* stage is resolved by its readers. Thread-safe: one lock
    per chunk.
    """

    def __init__(self, runner: Runner, node: StageNode, stage: FrameStage, inputs: dict[str, Value],
                 info: StreamInfo, *, forced: bool, lazy: bool):
        self.runner, self.node, self.stage, self.inputs, self.info = runner, node, stage, inputs, info
        self.forced, self.lazy = forced, lazy
        self.ranges = chunk_ranges(info.frames, runner.pipeline.chunk_frames)
        self.keys: list[str | None] = [None] * len(self.ranges)
        self.entries: list[Entry | None] = [None] * len(self.ranges)
        self._cached = [False] * len(self.ranges)  # per chunk: found stored (not computed) in this run
        self.report = Report(node.name, node.uses, "cached", chunks=len(self.ranges), frames=info.frames)
        self._locks = [threading.Lock() for _ in self.ranges]
        self._book = threading.Lock()  # guards the report, the bar and the dicts below
        self._upstream: dict[str, Any] | None = None
        self._streams: dict[str, ComputedStream] = {}
        self._readers: list[str] = []
        self._bar: tqdm | None = None
        self._verified: set[tuple[int, str]] = set()  # (chunk, port) read and hashed in this run
        self._depends: set[Path] = set()  # files recorded by runner.depends while chunks were computed
        runner.entries[node.name] = self.entries
        runner.redo[node.name] = self.redo

    # -- keys and digests ------------------------------------------------------------------

    def key(self, i: int, *, compute: bool = True) -> str | None:
        """Cache key of chunk ``i``; None if ``compute`` is False and an input chunk it reads
        is not stored yet."""
        if self.keys[i] is None:
            runner = self.runner
            plain = {p: v for p, v in self.inputs.items() if v.type != "frames"}
            digests = runner._digests(plain, compute=compute)
            start, stop = self.ranges[i]
            used = None if digests is None else runner._chunk_inputs(self.node, self.inputs, start, stop,
                                                                      compute=compute)
            if used is None:
                return None
            self.keys[i] = cache_key({**runner._material(self.node, digests), "chunk": [start, stop],
                                      "info": asdict(self.info), "chunk_inputs": used})
        return self.keys[i]

    def digests(self, port: str, lo: int, hi: int, *, compute: bool = True) -> list[str] | None:
        """Digests of output ``port`` in chunks ``lo..hi`` (inclusive), resolving them; None if
        ``compute`` is False and one is not stored yet."""
        out = []
        for i in range(lo, hi + 1):
            if not self.node.cls.cached:
                key = self.key(i, compute=compute)
                if key is None:
                    return None
                out.append(cache_key({"computed": key, "port": port}))
                continue
            entry = self.entry(i, compute=compute)
            if entry is None:
                return None
            out.append(entry.record["outputs"][port]["digest"])
        return out

    def digest(self, port: str, *, compute: bool = True) -> str | None:
        """Digest of the whole output ``port``: of its chunk digests and the stream shape."""
        digests = self.digests(port, 0, len(self.ranges) - 1, compute=compute)
        return None if digests is None else combine([*digests, json.dumps(asdict(self.info))])

    # -- resolving -------------------------------------------------------------------------

    def entry(self, i: int, *, compute: bool = True) -> Entry | None:
        """The stored entry of chunk ``i`` (cached stages), computed and committed if missing;
        None if ``compute`` is False (or in a dry run) and it is not stored."""
        if self.entries[i] is not None:
            return self.entries[i]
        compute = compute and not self.runner.opts.dry_run
        with self._locks[i]:
            if self.entries[i] is None:
                key = self.key(i, compute=compute)
                found = None if key is None or self.forced else self.runner.lookup(self.node, key)
                if found is None and not compute:
                    return None
                ran = found is None
                if ran:
                    found, ran = self._compute(i, key)
                self._resolved(i, found, ran)
            return self.entries[i]

    def resolve_all(self) -> None:
        """Resolve every chunk now, ``--jobs`` at once."""
        for _ in _map_ordered(self.entry, list(range(len(self.ranges))), jobs=self.runner.opts.jobs):
            pass

    def complete(self) -> bool:
        return all(entry is not None for entry in self.entries)

    def _compute(self, i: int, key: str) -> tuple[Entry, bool]:
        """Compute chunk ``i`` under its entry's lock, unless another run stored it meanwhile."""
        store, node = self.runner.store, self.node
        start, stop = self.ranges[i]
        with store.locked(key, on_wait=self.runner._waiting(node)):
            entry = None if self.forced else self.runner.lookup(node, key)
            if entry is not None:
                return entry, False
            timing = _own_time(self._spent) if self.lazy else contextlib.nullcontext()
            with timing, store.writing(key) as tmp:
                with _stage_errors(node):
                    with recording(set()) as files:
                        result = self.stage.process(start, stop, self._inputs(), dict(node.params),
                                                    self.runner._context(tmp, lambda n: None))
                    record = save_outputs(node.cls.outputs, result, tmp, frames=(stop - start, self.info))
                with self._book:  # a stage may read such a file once, for all its chunks
                    self._depends |= files
                    files = set(self._depends)
                entry = store.commit(key, tmp, {"stage": node.name, "uses": node.uses, "range": [start, stop],
                                                **record, "depends": self.runner.depends_digests(files)},
                                     replace=self.forced)
        return entry, True

    def redo(self, i: int) -> Entry:
        """Recompute chunk ``i``, whose stored entry was found damaged; the new entry."""
        with self._locks[i]:
            damaged = self.entries[i]
            if damaged is not None:
                self.runner.store.discard(damaged)
                self.entries[i] = None
                with self._book:
                    self.report.chunks_cached -= self._cached[i]
        return self.entry(i)

    def _resolved(self, i: int, entry: Entry, ran: bool) -> None:
        runner = self.runner
        with self._book:
            self.entries[i] = entry
            self._cached[i] = not ran
            self.report.chunks_cached += not ran
            if runner.opts.dry_run:
                return
            start, stop = self.ranges[i]
            runner.opts.log({"event": "chunk", "stage": self.node.name, "start": start, "stop": stop,
                             "status": "ran" if ran else "cached"})
            if self._bar is None:
                self._bar = runner._bar(self.node, self.info.frames)
            self._bar.update(stop - start)
            if ran and self.lazy and runner.current not in (None, self.node.name, *self._readers):
                self._readers.append(runner.current)
        runner.store.touch(entry)

    def _spent(self, seconds: float) -> None:
        with self._book:
            self.report.seconds += seconds

    def _inputs(self) -> dict[str, Any]:
        """What ``process`` is handed: frame streams, loaded bundles, paths (loaded once)."""
        if self._upstream is None:
            self._upstream = {port: v.get() for port, v in self.inputs.items()}
        return self._upstream

    def finish(self) -> Report:
        """The stage's report once every chunk is resolved; remembers its key material and
        hands its entries to publishing."""
        report, count = self.report, len(self.ranges)
        report.status = "cached" if report.chunks_cached == count else "ran" if report.chunks_cached == 0 else "partial"
        if self._readers:
            report.reason = f"computed while {', '.join(self._readers)} read it"
        self.close()
        self.runner._remember(self.node, self.runner._material(self.node, self.runner._digests(self.inputs)))
        return report

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()

    # -- outputs ---------------------------------------------------------------------------

    def stream(self, port: str) -> ChunkedStream:
        """Frames of output ``port``: of a cached stage, its stored chunks, each resolved (so
        computed and stored, if missing) when first read and read back from its entry (from
        the page cache: about one copy), verified on the first read; of an uncached stage,
        chunks computed as read."""
        if self.node.cls.cached:
            return StoredStream(self.info, self.ranges, lambda i: self._frames(i, port))
        with self._book:
            if port not in self._streams:
                self._streams[port] = ComputedStream(self.info, self.ranges, lambda i, p=port: self._computed(p, i),
                                                     keep=self.runner.opts.jobs + 2)
            return self._streams[port]

    def _frames(self, i: int, port: str) -> np.ndarray:
        """Frames ``(B, H, W, C)`` of output ``port`` in chunk ``i``: hashed against the entry's
        record on the first read in this run (a damaged entry is recomputed), memory-mapped
        after that."""
        self.entry(i)
        if (i, port) in self._verified:
            return load_mapped(self.entries[i], port)
        frames = self.runner.read_stored(self.node, i, lambda entry: load_frames(entry, port))
        self._verified.add((i, port))
        return frames

    def load(self, port: str) -> dict[str, np.ndarray]:
        """A bundle output, its chunks concatenated, once every chunk is resolved."""
        self.resolve_all()
        parts = [self.runner.read_stored(self.node, i, lambda entry: load_bundle(entry, port))
                 for i in range(len(self.ranges))]
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}

    def _computed(self, port: str, i: int) -> np.ndarray:
        """Frames ``(B, H, W, C)`` of output ``port`` in chunk ``i`` of an uncached stage."""
        start, stop = self.ranges[i]
        ctx = Context(device=self.runner.opts.device, files_dir=_no_files(self.node),
                      log=logging.getLogger(f"runner.stage.{self.node.name}"))
        with _stage_errors(self.node):
            frames = np.asarray(self.stage.process(start, stop, self._inputs(), dict(self.node.params), ctx)[port])
            check_frames(port, frames, stop - start, self.info)
        return frames


def _defines_stream_info(cls: type[FrameStage]) -> bool:
    """True if the stage computes its own output shape instead of taking its frames input's."""
    return cls.stream_info is not FrameStage.stream_info


def _after(stages: list[str | None]) -> str:
    names = ", ".join(dict.fromkeys(s for s in stages if s))
    return f"after {names}, which will run; cached if its output is unchanged"


def _no_files(node: StageNode) -> Callable[[str], Path]:
    def files_dir(port: str) -> Path:
        raise RuntimeError(f"{node.uses} has cached = False and cannot write files")

    return files_dir


_DISK_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO)


@contextlib.contextmanager
def _stage_errors(node: StageNode) -> Iterator[None]:
    """Turn a :class:`StageError`, or an :class:`OSError` of a full or failing disk, raised
    while ``node`` runs, is stored or is published into :class:`StageFailed` naming the stage
    (and the file)."""
    try:
        yield
    except StageError as exc:
        raise StageFailed(node, exc) from exc
    except OSError as exc:
        if exc.errno not in _DISK_ERRORS:
            raise
        where = f"{exc.filename}: " if exc.filename else ""
        raise StageFailed(node, StageError(f"{where}{exc.strerror or exc}")) from exc


def _map_ordered(fn: Callable[[int], Any], items: list[int], *, jobs: int):
    """Yield ``(item, fn(item))``; with ``jobs > 1`` up to ``jobs`` calls run in threads, at
    most ``2 * jobs`` submitted ahead (bounded memory). The first exception cancels the rest."""
    if jobs <= 1:
        for item in items:
            yield item, fn(item)
        return
    pool = ThreadPoolExecutor(max_workers=jobs)
    pending: dict[Future, int] = {}
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
