"""Scheduling: run (or, for ``--dry-run``, plan) a validated pipeline against the cache.

Stages run one after the other in topological order. A sequence stage is one cache entry; a
frame stage is one entry per chunk of ``chunk_frames`` frames, computed by ``--jobs`` threads,
so an interrupted run recomputes only the chunks it had not finished. A frame stage declaring
``cached = False`` (decoding) is not stored: its chunks are computed while a downstream stage
reads them, and keyed by their cache key instead of their bytes.

Every key (see :mod:`runner.digest`) includes the digests of the inputs actually used: a frame
stage's chunk depends on the upstream chunks its window overlaps, a sequence stage on the whole
upstream output. So a stage whose upstream re-ran but produced identical bytes is a cache hit.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import logging
import os
import shutil
import socket
import sys
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from runner.cache import CacheStore, Entry, holder_is_stale
from runner.config import Pipeline, StageNode
from runner.digest import array_digest, bundle_digest, cache_key, combine, file_digest, library_versions, tree_digest
from runner.stage import Context, FrameStage, StageError, StreamInfo
from runner.streams import CachedStream, ComputedStream, chunk_ranges

BUNDLE_FILE = "{port}.npz"
FRAMES_FILE = "{port}.npy"
MANIFEST = "manifest.json"


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


@dataclass
class Value:
    """What one output (or pipeline input) gives downstream stages.

    ``digest`` is None in a dry run when the producer has not run yet. Outputs of frame stages
    also carry one digest per chunk (``chunk_digests``) and the stream shape (``info``).
    """

    type: str
    digest: str | None
    load: Callable[[], Any] | None = None
    chunk_digests: list[str] | None = None
    info: StreamInfo | None = None
    _loaded: Any = field(default=None, repr=False)

    def get(self) -> Any:
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


class Runner:
    """Runs one pipeline with bound inputs; :meth:`run` returns one :class:`Report` per stage."""

    def __init__(self, pipeline: Pipeline, bound: dict[str, Path], options: Options):
        self.pipeline = pipeline
        self.opts = options
        self.store = options.cache
        self.values: dict[tuple[str | None, str], Value] = {}
        for name, path in bound.items():
            kind = pipeline.inputs[name].type
            digest = file_digest(path) if kind in ("video", "file") else tree_digest(path)
            self.values[(None, name)] = Value(kind, digest, load=lambda p=path: Path(p))
        self.entries: dict[str, list[Entry]] = {}
        self.memo_dir = self.store.root / "runs"

    def selected(self) -> list[StageNode]:
        names = self.pipeline.ancestors(self.opts.until) if self.opts.until else set(self.pipeline.stages)
        return [node for name, node in self.pipeline.stages.items() if name in names]

    def run(self) -> list[Report]:
        reports = []
        for node in self.selected():
            started = time.perf_counter()
            self.opts.log({"event": "stage_start", "stage": node.name, "uses": node.uses})
            try:
                if issubclass(node.cls, FrameStage):
                    report = self._frame_stage(node)
                else:
                    report = self._sequence_stage(node)
            except StageError as exc:
                raise StageFailed(node, exc) from exc
            report.seconds = time.perf_counter() - started
            self.opts.log({"event": "stage", **asdict(report)})
            self.opts.echo(report.line())
            reports.append(report)
        if not self.opts.dry_run and self.opts.out is not None:
            for node in self.selected():
                try:
                    self._publish(node)
                except StageError as exc:
                    raise StageFailed(node, exc) from exc
        return reports

    # -- keys ------------------------------------------------------------------------------

    def _inputs(self, node: StageNode) -> dict[str, Value]:
        return {port: self.values[(ref.stage, ref.port)] for port, ref in node.inputs.items()}

    def _material(self, node: StageNode, inputs: dict[str, Value]) -> dict[str, Any]:
        return {
            "stage": node.uses,
            "version": node.cls.version,
            "params": node.params,
            "inputs": {port: v.digest for port, v in inputs.items()},
            "device": self.opts.device,
            "libs": library_versions(),
        }

    def _memo_path(self, node: StageNode) -> Path:
        ident = f"{self.pipeline.path.resolve()}\n{node.name}"
        return self.memo_dir / f"{hashlib.sha256(ident.encode()).hexdigest()[:32]}.json"

    def _remember(self, node: StageNode, material: dict[str, Any]) -> None:
        """Keep the key material of this stage's last completed run, to explain dry runs."""
        self.memo_dir.mkdir(parents=True, exist_ok=True)
        path = self._memo_path(node)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(material, sort_keys=True))
        os.replace(tmp, path)

    def _why(self, node: StageNode, material: dict[str, Any]) -> str:
        try:
            old = json.loads(self._memo_path(node).read_text())
        except (OSError, ValueError):
            return "never run with this configuration"
        changes = []
        if (old.get("stage"), old.get("version")) != (material["stage"], material["version"]):
            changes.append(f"stage {old.get('stage')} {old.get('version')} -> {material['stage']} {material['version']}")
        old_params, new_params = old.get("params", {}), material["params"]
        for name in sorted(set(old_params) | set(new_params)):
            if old_params.get(name) != new_params.get(name):
                changes.append(f"param {name}: {old_params.get(name)!r} -> {new_params.get(name)!r}")
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
        report = Report(node.name, node.uses, "cached")
        unknown = [ref.stage for ref in node.inputs.values() if self.values[(ref.stage, ref.port)].digest is None]
        if unknown:
            self._set_unknown(node)
            return Report(node.name, node.uses, "may run", _after(unknown))
        material = self._material(node, inputs)
        key = cache_key(material)
        entry = None if forced else self.store.lookup(key)
        if self.opts.dry_run:
            if entry is None:
                self._set_unknown(node)
                return Report(node.name, node.uses, "will run", "forced (--force)" if forced else self._why(node, material))
            self._set_outputs(node, [entry], None)
            return Report(node.name, node.uses, "cached", "cache hit")
        if entry is None:
            frames = next((v.info.frames for v in inputs.values() if v.info is not None), None)
            with self._bar(node, frames) as bar, self.store.locked(key, on_wait=self._waiting(node)):
                entry = None if forced else self.store.lookup(key)
                if entry is None:
                    with self.store.writing(key) as tmp:
                        ctx = self._context(tmp, bar.update)
                        values = {port: v.get() for port, v in inputs.items()}
                        result = node.cls().run(values, dict(node.params), ctx)
                        record = _save_outputs(node, result, tmp, frames=None)
                        entry = self.store.commit(key, tmp, {"stage": node.name, "uses": node.uses, **record},
                                                  replace=forced)
                    report.status = "ran"
        self.store.touch(entry)
        self._remember(node, material)
        self._set_outputs(node, [entry], None)
        return report

    # -- frame stages ----------------------------------------------------------------------

    def _frame_stage(self, node: StageNode) -> Report:
        inputs = self._inputs(node)
        forced = node.name in self.opts.force
        unknown = [ref.stage for ref in node.inputs.values() if self.values[(ref.stage, ref.port)].digest is None]
        if unknown:
            self._set_unknown(node)
            return Report(node.name, node.uses, "may run", _after(unknown))
        stage = node.cls()
        material = {**self._material(node, inputs), "chunk_frames": self.pipeline.chunk_frames}
        info = self._stream_info(node, stage, inputs, material)
        ranges = chunk_ranges(info.frames, self.pipeline.chunk_frames)
        # A chunk's key names its frames inputs by the chunks it reads, not by whole streams.
        per_chunk = {**material, "inputs": {p: v.digest for p, v in inputs.items() if v.type != "frames"}}
        keys = [cache_key({**per_chunk, "chunk": [s, e], "info": asdict(info),
                           "chunk_inputs": self._chunk_inputs(node, inputs, s, e)}) for s, e in ranges]
        values = {port: v.get() for port, v in inputs.items()}
        if not node.cls.cached:
            self._set_computed(node, stage, values, info, ranges, keys)
            reason = "computed while downstream stages read it"
            return Report(node.name, node.uses, "on demand", reason, frames=info.frames)

        entries = [None if forced else self.store.lookup(k) for k in keys]
        cached = sum(e is not None for e in entries)
        report = Report(node.name, node.uses, "cached", chunks=len(keys), chunks_cached=cached, frames=info.frames)
        if self.opts.dry_run:
            if cached == len(keys):
                self._set_outputs(node, entries, info)
                report.reason = "cache hit"
            else:
                self._set_unknown(node)
                report.status = "will run"
                if forced:
                    report.reason = "forced (--force)"
                elif cached:
                    report.reason = f"{len(keys) - cached} of {len(keys)} chunks missing (earlier run incomplete)"
                else:
                    report.reason = self._why(node, material)
            return report

        for (s, e), key, entry in zip(ranges, keys, entries):
            if entry is not None:
                self.opts.log({"event": "chunk", "stage": node.name, "start": s, "stop": e, "status": "cached"})
        missing = [i for i, e in enumerate(entries) if e is None]
        if missing:
            with self._bar(node, info.frames) as bar:
                bar.update(sum(ranges[i][1] - ranges[i][0] for i, e in enumerate(entries) if e is not None))

                def one(i: int) -> tuple[Entry, bool]:
                    entry, ran = self._chunk(node, stage, values, info, ranges[i], keys[i], forced)
                    s, e = ranges[i]
                    self.opts.log({"event": "chunk", "stage": node.name, "start": s, "stop": e,
                                   "status": "ran" if ran else "cached"})
                    bar.update(e - s)
                    return entry, ran

                for i, (entry, ran) in _map_ordered(one, missing, jobs=self.opts.jobs):
                    entries[i] = entry
                    if not ran:  # another run computed it meanwhile
                        report.chunks_cached += 1
            report.status = "ran" if report.chunks_cached == 0 else "partial"
        for entry in entries:
            self.store.touch(entry)
        self._remember(node, material)
        self._set_outputs(node, entries, info)
        return report

    def _stream_info(self, node: StageNode, stage: FrameStage, inputs: dict[str, Value],
                     material: dict[str, Any]) -> StreamInfo:
        """The stage's output stream shape; cached when the stage computes it itself (probing
        a video), taken from the frames input otherwise."""
        if not _defines_stream_info(node.cls):
            return next(v.info for port, v in inputs.items() if node.cls.inputs[port] == "frames")
        key = cache_key({**material, "stream_info": True})
        entry = self.store.lookup(key)
        if entry is None:
            info = stage.stream_info({port: v.get() for port, v in inputs.items()}, dict(node.params))
            if self.opts.dry_run:
                return info
            with self.store.writing(key) as tmp:
                entry = self.store.commit(key, tmp, {"stage": node.name, "uses": node.uses, "info": asdict(info)})
        return StreamInfo(**entry.record["info"])

    def _chunk_inputs(self, node: StageNode, inputs: dict[str, Value], start: int, stop: int) -> dict[str, Any]:
        """Digests of the upstream frame chunks that frames ``[start - window, stop + window)``
        touch (clamped to the clip). A stage that defines its own stream shape may map output
        frames to any input frames, so each of its chunks depends on whole input streams."""
        own_shape = _defines_stream_info(node.cls)
        used = {}
        for port, v in inputs.items():
            if v.type != "frames":
                continue
            if own_shape:
                used[port] = {"info": asdict(v.info), "stream": v.digest}
                continue
            size, window = self.pipeline.chunk_frames, node.cls.window
            lo = max(0, start - window) // size
            hi = (min(v.info.frames, stop + window) - 1) // size
            used[port] = {"info": asdict(v.info), "chunks": v.chunk_digests[lo:hi + 1]}
        return used

    def _chunk(self, node: StageNode, stage: FrameStage, values: dict[str, Any], info: StreamInfo,
               span: tuple[int, int], key: str, forced: bool) -> tuple[Entry, bool]:
        with self.store.locked(key, on_wait=self._waiting(node)):
            entry = None if forced else self.store.lookup(key)
            if entry is not None:
                return entry, False
            with self.store.writing(key) as tmp:
                result = stage.process(span[0], span[1], values, dict(node.params), self._context(tmp, lambda n: None))
                record = _save_outputs(node, result, tmp, frames=(span[1] - span[0], info))
                record = {"stage": node.name, "uses": node.uses, "range": list(span), **record}
                return self.store.commit(key, tmp, record, replace=forced), True

    # -- outputs ---------------------------------------------------------------------------

    def _set_unknown(self, node: StageNode) -> None:
        for port, kind in node.cls.outputs.items():
            self.values[(node.name, port)] = Value(kind, None)

    def _set_outputs(self, node: StageNode, entries: list[Entry], info: StreamInfo | None) -> None:
        """Publish a stage's cached outputs to downstream stages (loaded only when read)."""
        self.entries[node.name] = entries
        for port, kind in node.cls.outputs.items():
            digests = [e.record["outputs"][port]["digest"] for e in entries]
            if info is None:
                digest, chunk_digests = digests[0], None
            else:
                digest, chunk_digests = combine([*digests, json.dumps(asdict(info))]), digests
            paths = [e.path / e.record["outputs"][port]["file"] for e in entries]
            if kind == "frames":
                load = lambda p=paths, r=[tuple(e.record["range"]) for e in entries]: CachedStream(info, r, p)
            elif kind == "files":
                load = lambda p=paths: p[0]
            else:
                load = lambda p=paths: _load_bundle(p)
            self.values[(node.name, port)] = Value(kind, digest, load, chunk_digests, info)

    def _set_computed(self, node: StageNode, stage: FrameStage, values: dict[str, Any], info: StreamInfo,
                      ranges: list[tuple[int, int]], keys: list[str]) -> None:
        """Outputs of an uncached frame stage: streams computing chunks as they are read."""
        params = dict(node.params)
        ctx = Context(device=self.opts.device, files_dir=_no_files(node),
                      log=logging.getLogger(f"runner.stage.{node.name}"))

        for port in node.cls.outputs:
            def compute(i: int, port: str = port) -> np.ndarray:
                start, stop = ranges[i]
                try:
                    frames = np.asarray(stage.process(start, stop, values, params, ctx)[port])
                except StageError as exc:
                    raise StageFailed(node, exc) from exc
                _check_frames(node, port, frames, stop - start, info)
                return frames

            digests = [cache_key({"computed": k, "port": port}) for k in keys]
            stream = ComputedStream(info, ranges, compute, keep=self.opts.jobs + 2)
            digest = combine([*digests, json.dumps(asdict(info))])
            self.values[(node.name, port)] = Value("frames", digest, lambda s=stream: s, digests, info)

    def _publish(self, node: StageNode) -> None:
        """Copy a stage's ``files`` outputs to ``--out/<stage>/`` (one port) or
        ``--out/<stage>/<port>/`` (several), writing ``manifest.json`` last and moving the
        folder into place whole, so a partial output folder never looks complete."""
        ports = [p for p, kind in node.cls.outputs.items() if kind == "files"]
        entries = self.entries.get(node.name)
        if not ports or not entries:
            return
        out = Path(self.opts.out)
        final = out / node.name
        keys = [e.key for e in entries]
        try:
            if json.loads((final / MANIFEST).read_text()).get("keys") == keys:
                return
        except (OSError, ValueError):
            pass
        out.mkdir(parents=True, exist_ok=True)
        for leftover in out.glob(f".{node.name}.*"):  # from runs killed while publishing
            pid = leftover.name.split(".")[2]
            if pid.isdigit() and holder_is_stale({"pid": int(pid), "host": socket.gethostname()}):
                shutil.rmtree(leftover, ignore_errors=True)
        tmp = out / f".{node.name}.{os.getpid()}.tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        listed = []
        for port in ports:
            target = tmp if len(ports) == 1 else tmp / port
            for entry in entries:
                source = entry.path / entry.record["outputs"][port]["file"]
                for rel, size, digest in entry.record["outputs"][port]["files"]:
                    dest = target / rel
                    if dest.exists():
                        raise StageError(f"{port}: two chunks wrote the same file {rel!r}")
                    dest.parent.mkdir(parents=True, exist_ok=True)
                    shutil.copyfile(source / rel, dest)
                    listed.append({"path": dest.relative_to(tmp).as_posix(), "size": size, "sha256": digest})
        manifest = {"stage": node.name, "uses": node.uses, "keys": keys, "files": listed}
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=1))
        old = out / f".{node.name}.{os.getpid()}.old"
        shutil.rmtree(old, ignore_errors=True)
        try:
            os.replace(final, old)
        except FileNotFoundError:
            pass
        try:
            os.replace(tmp, final)
        except OSError:  # another run published the same stage meanwhile
            shutil.rmtree(tmp, ignore_errors=True)
        shutil.rmtree(old, ignore_errors=True)

    # -- helpers ---------------------------------------------------------------------------

    def _context(self, tmp: Path, progress: Callable[[int], None]) -> Context:
        def files_dir(port: str) -> Path:
            folder = tmp / "files" / port
            folder.mkdir(parents=True, exist_ok=True)
            return folder

        return Context(device=self.opts.device, files_dir=files_dir, progress=progress)

    def _bar(self, node: StageNode, total: int | None) -> tqdm:
        return tqdm(total=total, desc=node.name, unit="frame", file=sys.stderr, leave=False,
                    disable=not self.opts.progress, dynamic_ncols=True)

    def _waiting(self, node: StageNode) -> Callable[[dict[str, Any]], None]:
        def on_wait(holder: dict[str, Any]) -> None:
            self.opts.log({"event": "wait", "stage": node.name, "holder_pid": holder.get("pid")})

        return on_wait


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


def _check_frames(node: StageNode, port: str, frames: np.ndarray, count: int, info: StreamInfo) -> None:
    if frames.ndim != 4 or frames.shape[0] != count or frames.shape[1:3] != (info.height, info.width):
        raise StageFailed(node, StageError(
            f"output {port!r}: expected frames ({count}, {info.height}, {info.width}, C), got {frames.shape}"))


def _save_outputs(node: StageNode, result: Any, tmp: Path, *, frames: tuple[int, StreamInfo] | None) -> dict[str, Any]:
    """Store a stage's result in the entry folder ``tmp``; return the record's ``outputs``.

    ``frames`` is ``(chunk length, stream info)`` for a frame stage's chunk, None for a sequence
    stage.
    """
    declared = node.cls.outputs
    if not isinstance(result, dict) or set(result) != set(declared):
        got = sorted(result) if isinstance(result, dict) else type(result).__name__
        raise StageError(f"returned {got}, expected outputs {sorted(declared)}")
    outputs = {}
    for port, kind in declared.items():
        value = result[port]
        if kind == "frames":
            array = np.asarray(value)
            _check_frames(node, port, array, frames[0], frames[1])
            name = FRAMES_FILE.format(port=port)
            np.save(tmp / name, array, allow_pickle=False)
            outputs[port] = {"type": kind, "file": name, "digest": array_digest(array)}
        elif kind == "files":
            folder = tmp / "files" / port
            folder.mkdir(parents=True, exist_ok=True)
            listed = []
            for path in sorted(p for p in folder.rglob("*") if p.is_file()):
                listed.append([path.relative_to(folder).as_posix(), path.stat().st_size, file_digest(path)])
            digest = cache_key([[rel, sha] for rel, _, sha in listed])
            outputs[port] = {"type": kind, "file": f"files/{port}", "digest": digest, "files": listed}
        else:
            if not isinstance(value, dict):
                raise StageError(f"output {port!r} ({kind}): expected a dict of arrays, got {type(value).__name__}")
            arrays = {k: np.asarray(v) for k, v in value.items()}
            bad = [k for k, a in arrays.items() if a.dtype.hasobject]
            if bad:
                raise StageError(f"output {port!r}: {bad[0]!r} is an object array (not storable without pickle)")
            if frames is not None:
                wrong = [k for k, a in arrays.items() if a.ndim == 0 or a.shape[0] != frames[0]]
                if wrong:
                    raise StageError(f"output {port!r}: {wrong[0]!r} must have {frames[0]} rows (one per frame)")
            name = BUNDLE_FILE.format(port=port)
            np.savez(tmp / name, **arrays)
            outputs[port] = {"type": kind, "file": name, "digest": bundle_digest(arrays)}
    return {"outputs": outputs}


def _load_bundle(paths: list[Path]) -> dict[str, np.ndarray]:
    """A bundle from one ``.npz`` (sequence stage) or the concatenation of per-chunk ones."""
    parts = []
    for path in paths:
        with np.load(path, allow_pickle=False) as data:
            parts.append({k: data[k] for k in data.files})
    if len(parts) == 1:
        return parts[0]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


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
