"""Storing a stage's outputs in a cache entry, and reading them back verified.

Every data file of an entry has its sha256 in the entry's completion record: a bundle
``<port>.npz`` under ``outputs.<port>.sha256``, the files of a ``files`` output under
``outputs.<port>.files`` (``[relative path, size, sha256]``). Readers hash the bytes they read
(one read: the array is built on the buffer that was hashed) and raise :class:`Damaged` on a
mismatch or a file that cannot be parsed, so the runner recomputes the entry instead of handing
damaged data on. A ``frames`` output is not stored: the record keeps its digest only (its frames
are handed to the stages reading them as they are computed, :mod:`runner.broadcast`).
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import io
import os
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from runner.bundle import BundleType
from runner.cache import Entry
from runner.digest import array_digest, bundle_digest, cache_key, file_digest
from runner.stage import Context, StageError, StreamInfo

BUNDLE_FILE = "{port}.npz"
FICLONE = 0x40049409  # Linux ioctl: make the destination a copy-on-write clone of the source
_BLOCK = 1 << 20  # bytes read at a time while a file is copied


class Damaged(Exception):
    """A stored file does not match the sha256 its entry recorded, or cannot be parsed."""

    def __init__(self, path: Path, reason: str):
        self.path = path
        super().__init__(f"{path}: {reason}")


@contextlib.contextmanager
def _naming(path: Path) -> Iterator[None]:
    """Give an :class:`OSError` raised while writing ``path`` (disk full) the file's name."""
    try:
        yield
    except OSError as exc:
        if exc.filename is not None:
            raise
        raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc


def check_frames(port: str, frames: np.ndarray, count: int, info: StreamInfo) -> None:
    """Raise :class:`StageError` unless ``frames`` is ``(count, info.height, info.width, C)``."""
    if frames.ndim != 4 or frames.shape[0] != count or frames.shape[1:3] != (info.height, info.width):
        raise StageError(f"output {port!r}: expected frames ({count}, {info.height}, {info.width}, C), got {frames.shape}")


def save_outputs(
    declared: Mapping[str, str | BundleType], result: Any, tmp: Path, *, frames: tuple[int, StreamInfo] | None
) -> dict[str, Any]:
    """Store a stage's result in the entry folder ``tmp``; return the record's ``outputs``.

    Parameters
    ----------
    declared
        The stage's output ports, name -> type. A bundle of a declared :class:`BundleType` is
        checked against it (:meth:`BundleType.problems`).
    result
        What the stage returned: per port an array (frames: checked and digested, not stored),
        a dict of arrays (bundle) or None (``files``, already written under
        ``tmp/files/<port>/``).
    frames
        ``(chunk length, stream info)`` for a frame stage's chunk, None for a sequence stage.

    Raises
    ------
    StageError
        The result does not match the declared outputs.
    """
    if not isinstance(result, dict) or set(result) != set(declared):
        got = sorted(result) if isinstance(result, dict) else type(result).__name__
        raise StageError(f"returned {got}, expected outputs {sorted(declared)}")
    outputs: dict[str, dict[str, Any]] = {}
    for port, kind in declared.items():
        value = result[port]
        if kind == "frames":
            array = np.asarray(value)
            check_frames(port, array, frames[0], frames[1])  # type: ignore[index]  # a frame stage is given its frames
            outputs[port] = {"type": kind, "digest": array_digest(array)}
        elif kind == "files":
            folder = tmp / "files" / port
            folder.mkdir(parents=True, exist_ok=True)
            files = sorted(p for p in folder.rglob("*") if p.is_file())
            listed = [[path.relative_to(folder).as_posix(), path.stat().st_size, file_digest(path)] for path in files]
            digest = cache_key([[rel, sha] for rel, _, sha in listed])
            outputs[port] = {"type": kind, "file": f"files/{port}", "digest": digest, "files": listed}
        else:
            arrays = _bundle_arrays(port, kind, value, frames)
            name = BUNDLE_FILE.format(port=port)
            with _naming(tmp / name):
                np.savez(tmp / name, **arrays)  # type: ignore[arg-type]  # numpy declares the keyword arrays too narrowly
            outputs[port] = {"type": str(kind), "file": name, "digest": bundle_digest(arrays), "sha256": file_digest(tmp / name)}
    return {"outputs": outputs}


def _bundle_arrays(port: str, kind: str | BundleType, value: Any, frames: tuple[int, StreamInfo] | None) -> dict[str, np.ndarray]:
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
    if isinstance(kind, BundleType):
        problems = kind.problems(arrays)
        if problems:
            raise StageError(f"output {port!r} ({kind.name}): {'; '.join(problems)}")
    return arrays


def output_path(entry: Entry, port: str) -> Path:
    """The file (or ``files`` folder) of output ``port`` in ``entry``."""
    return entry.path / entry.record["outputs"][port]["file"]  # type: ignore[no-any-return]  # the record is JSON


def _read_verified(path: Path, sha256: str | None) -> bytearray:
    """The bytes of ``path``, read once into a writable buffer and checked against ``sha256``."""
    if not sha256:
        raise Damaged(path, "no sha256 recorded")
    try:
        with open(path, "rb") as f:
            size = f.seek(0, io.SEEK_END)
            f.seek(0)
            data = bytearray(size)
            got = f.readinto(data)
    except OSError as exc:
        raise Damaged(path, f"cannot read ({exc.strerror or exc})") from None
    if got != size or hashlib.sha256(data).hexdigest() != sha256:
        raise Damaged(path, "sha256 differs from the one recorded when it was stored")
    return data


def load_bundle(entry: Entry, port: str) -> dict[str, np.ndarray]:
    """Bundle ``port`` of ``entry``, verified. Raises :class:`Damaged`."""
    path = output_path(entry, port)
    data = _read_verified(path, entry.record["outputs"][port].get("sha256"))
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as stored:
            return {k: stored[k] for k in stored.files}
    except (ValueError, OSError, EOFError) as exc:
        raise Damaged(path, f"not a readable .npz ({exc})") from None


def verify_files(entry: Entry, port: str) -> Path:
    """The folder of ``files`` output ``port`` once every file in it matches its recorded size
    and sha256. Raises :class:`Damaged`."""
    folder = output_path(entry, port)
    for rel, _, sha256 in entry.record["outputs"][port]["files"]:
        _read_verified(folder / rel, sha256)
    return folder


def file_stat(path: Path) -> list[int]:
    """``[size, mtime_ns, ctime_ns, inode]`` of ``path``: what changes when a file is written or
    replaced. ``ctime`` cannot be set back (``utime`` itself sets it to now), so a file whose
    bytes were changed and its times restored afterwards has another stat."""
    stat = os.stat(path)
    return [stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns, stat.st_ino]


def copy_verified(source: Path, dest: Path, sha256: str) -> None:
    """Publish cache file ``source`` at ``dest``, hashing every byte on the way: a copy-on-write
    clone (``FICLONE``: the two share their blocks until one is written; Btrfs, XFS, bcachefs)
    is hashed where the filesystem makes one, else the bytes are hashed as they are copied. A
    published file and its entry never share their bytes, so a tool that rewrites one in place
    cannot damage the other.

    Raises
    ------
    Damaged
        ``source`` is missing, cannot be read or its bytes differ from ``sha256``.
    OSError
        Writing ``dest`` failed (a full disk); the error names ``dest``.
    """
    try:
        src = open(source, "rb")
    except OSError as exc:
        raise Damaged(source, "missing" if isinstance(exc, FileNotFoundError) else f"cannot read ({exc.strerror})") from None
    with src, _naming(dest), open(dest, "wb") as dst:
        got = _clone_hashed(src, dst, dest) or _copy_hashed(src, dst, source)
    if got != sha256:
        raise Damaged(source, "sha256 differs from the one recorded when it was stored")


def _clone_hashed(src: io.BufferedReader, dst: io.BufferedWriter, dest: Path) -> str | None:
    """Make ``dst`` a copy-on-write clone of ``src`` and return the clone's sha256, or None
    where the filesystem makes no clone."""
    try:
        fcntl.ioctl(dst.fileno(), FICLONE, src.fileno())
    except OSError:
        return None
    return file_digest(dest)


def _copy_hashed(src: io.BufferedReader, dst: io.BufferedWriter, source: Path) -> str:
    """Copy ``src`` into ``dst`` block by block; the sha256 of the bytes copied."""
    h = hashlib.sha256()
    while True:
        try:
            block = src.read(_BLOCK)
        except OSError as exc:
            raise Damaged(source, f"cannot read ({exc.strerror or exc})") from None
        if not block:
            return h.hexdigest()
        h.update(block)
        dst.write(block)


def read_or_redo(
    read: Callable[[Entry], Any], entry: Entry, *, redo: Callable[[], Entry], on_damaged: Callable[[Damaged], None]
) -> Any:
    """``read(entry)``; if that raises :class:`Damaged`, report it to ``on_damaged``, recompute
    the entry with ``redo`` and read the new one. Raises :class:`StageError` if the new entry is
    damaged too (a failing disk)."""
    try:
        return read(entry)
    except Damaged as exc:
        on_damaged(exc)
    try:
        return read(redo())
    except Damaged as exc:
        raise StageError(f"cache entry damaged again right after it was computed: {exc}") from None


def entry_context(tmp: Path, *, device: str, progress: Callable[[int], None]) -> Context:
    """The :class:`Context` of a stage computing the entry written in ``tmp``: its ``files``
    outputs go to ``tmp/files/<port>/``."""

    def files_dir(port: str) -> Path:
        folder = tmp / "files" / port
        folder.mkdir(parents=True, exist_ok=True)
        return folder

    return Context(device=device, files_dir=files_dir, progress=progress)
