"""Cache keys of one run: what goes into a stage's key, whether a stored entry is still current,
and why a key changed (the dry run's reasons).

A key is :func:`runner.digest.cache_key` of the *material* built here: the cache format, stage
name and version, parameters (those declared ``in_key``), input digests, the digests of
parameter files (``Param(file=True)``), the device, the library versions and, for frame stages,
the chunk size; callers add the chunk range and the upstream chunks read. An entry also records
the files its computation read besides its inputs (:mod:`runner.depends`); :meth:`Keys.lookup`
hashes them again and treats an entry whose files changed as missing.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

from runner.cache import CacheStore, Entry
from runner.config import StageNode
from runner.digest import file_digest, library_versions
from runner.stage import FrameStage

# Part of every key: entries stored by an older layout of the cache (no sha256 per data file)
# are never looked up.
CACHE_FORMAT = 2


class Keys:
    """Key material, entry lookup and dry-run reasons for the stages of one pipeline run.

    Parameters
    ----------
    store
        The cache; the last completed run of each stage is remembered under ``runs/`` in it.
    pipeline
        The pipeline file (with the stage name, it identifies a stage across runs).
    device, chunk_frames
        The resolved device and the pipeline's chunk size, part of every key.
    discard_stale
        Whether :meth:`lookup` removes a stale entry (the planner only reports it).
    """

    def __init__(self, store: CacheStore, pipeline: Path, *, device: str, chunk_frames: int, discard_stale: bool = True):
        self.store = store
        self.memo_dir = store.root / "runs"
        self.pipeline = Path(pipeline).resolve()
        self.device, self.chunk_frames, self.discard_stale = device, chunk_frames, discard_stale
        self._file_digests: dict[Path, str | None] = {}  # files recorded by runner.depends, hashed once
        self._stale: dict[str, str] = {}  # per stage, why a stored entry was stale

    def material(self, node: StageNode, digests: dict[str, str]) -> dict[str, Any]:
        """The key material of ``node`` given its input digests (port -> digest)."""
        schema = {p.name: p for p in node.cls.params}
        material = {
            "cache_format": CACHE_FORMAT,
            "stage": node.uses,
            "version": node.cls.version,
            "params": {k: v for k, v in node.params.items() if k not in schema or schema[k].in_key},
            "inputs": digests,
            "device": self.device,
            "libs": library_versions(),
        }
        files = {
            k: file_digest(Path(v))
            for k, v in node.params.items()
            if k in schema and schema[k].file and isinstance(v, str) and Path(v).is_file()
        }
        if files:
            material["param_files"] = files
        if issubclass(node.cls, FrameStage):
            material["chunk_frames"] = self.chunk_frames
        return material

    # -- files recorded while an entry was computed -------------------------------------------

    def lookup(self, node: StageNode, key: str) -> Entry | None:
        """The complete entry for ``key`` if the files it recorded (:mod:`runner.depends`)
        are unchanged; a stale entry is removed (unless ``discard_stale`` is false) and None returned."""
        entry = self.store.lookup(key)
        if entry is None:
            return None
        recorded = entry.record.get("depends", {})
        changed = [path for path, sha256 in recorded.items() if self._sha256(Path(path)) != sha256]
        if not changed:
            return entry
        self._stale[node.name] = f"file {changed[0]} changed"
        if self.discard_stale:
            self.store.discard(entry)
        return None

    def depends(self, files: set[Path]) -> dict[str, str | None]:
        """``{path: sha256}`` of the files a computation recorded (None: missing), for its record."""
        return {str(path): self._sha256(path) for path in sorted(files)}

    def _sha256(self, path: Path) -> str | None:
        if path not in self._file_digests:
            try:
                self._file_digests[path] = file_digest(path)
            except OSError:
                self._file_digests[path] = None
        return self._file_digests[path]

    # -- the last completed run of each stage ---------------------------------------------------

    def _memo_path(self, node: StageNode) -> Path:
        ident = f"{self.pipeline}\n{node.name}"
        return self.memo_dir / f"{hashlib.sha256(ident.encode()).hexdigest()[:32]}.json"

    def memo(self, node: StageNode) -> dict[str, Any] | None:
        """The key material remembered from ``node``'s last completed run, or None."""
        try:
            material: dict[str, Any] = json.loads(self._memo_path(node).read_text())
            return material
        except (OSError, ValueError):
            return None

    def remember(self, node: StageNode, material: dict[str, Any]) -> None:
        """Keep the key material of this stage's last completed run, to explain dry runs."""
        self.memo_dir.mkdir(parents=True, exist_ok=True)
        path = self._memo_path(node)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(material, sort_keys=True))
        os.replace(tmp, path)

    def why(self, node: StageNode, material: dict[str, Any]) -> str:
        """Why ``node``'s entry for ``material`` is missing: a stale recorded file, or what
        changed since its last completed run."""
        if node.name in self._stale:
            return self._stale[node.name]
        old = self.memo(node)
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
