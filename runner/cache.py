"""Content-addressed cache store: atomic entries, completion records, per-entry locks.

Layout under the cache root (``--cache-dir``, ``$RUNNER_CACHE_DIR``, default ``.cache/runner``)::

    entries/<key[:2]>/<key>/           one entry: data files + complete.json (written last)
    tmp/<key>.<pid>.<token>/           an entry being written; moved into place with os.replace
    locks/<key>.lock                   JSON {pid, host, started}: who is computing <key>
    published/<sha256 of a folder>.json   stat records of the files last published in an --out folder

An entry is written in ``tmp/``; its completion record ``complete.json`` is written last and
the folder is then renamed into ``entries/`` in one ``os.replace``, so an entry is whole or
absent, whatever moment a process dies. Data is ``.npy``/``.npz`` (never pickled), files, JSON.

A lock names its holder's PID, host and process start time. A lock whose holder on this host
is gone (or whose PID now belongs to a younger process) is stale and is removed by the next
process that wants the entry; stale locks are broken under a host-wide ``flock`` so that two
processes never both break one and steal a fresh lock.

A lock of another host (a cluster node) cannot be judged by its PID: its holder refreshes it, a
heartbeat, every quarter of the lease (``lease_s``, ``$RUNNER_LOCK_LEASE_S``, default
:data:`LEASE_S`), by setting the lock file's mtime, and a process waiting for it breaks it when
it has seen no change of the file (its mtime and bytes) for a whole lease, timed on its own
monotonic clock. So a node killed mid-chunk (its holder gone with its host) holds up the others
for one lease, and no two hosts' clocks are ever compared: a node whose clock is off neither
breaks a live lock nor keeps a dead one.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import secrets
import shutil
import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

COMPLETE = "complete.json"
ENV_VAR = "RUNNER_CACHE_DIR"
LEASE_ENV_VAR = "RUNNER_LOCK_LEASE_S"
DEFAULT_DIR = Path(".cache/runner")
POLL_S = 0.05
LEASE_S = 60.0  # a lock of another host unchanged this long (no heartbeat) is stale


def default_cache_dir() -> Path:
    return Path(os.environ.get(ENV_VAR) or DEFAULT_DIR)


@dataclass
class Entry:
    """A complete cache entry: its folder and its completion record."""

    key: str
    path: Path
    record: dict[str, Any]


def _process_start(pid: int) -> int | None:
    """Start time of ``pid`` in clock ticks since boot (Linux ``/proc``), None if unknown."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return int(stat.rpartition(")")[2].split()[19])


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def holder_is_stale(holder: dict[str, Any]) -> bool:
    """True if the process named in a lock (or tmp folder) record is gone from this host."""
    if holder.get("host") != socket.gethostname():
        return False
    pid = int(holder.get("pid", -1))
    if pid <= 0 or not _pid_alive(pid):
        return True
    started = holder.get("started")
    return started is not None and _process_start(pid) not in (None, started)


def lease_seconds() -> float:
    """The lock lease: ``$RUNNER_LOCK_LEASE_S`` if set (a positive number), else :data:`LEASE_S`."""
    text = os.environ.get(LEASE_ENV_VAR)
    try:
        value = float(text) if text else LEASE_S
    except ValueError:
        value = LEASE_S
    return value if value > 0 else LEASE_S


class _Heartbeat:
    """One thread per process refreshing the mtime of every lock the process holds, every
    quarter of the shortest lease among them; it ends when the process holds none (a run forks
    its child process only where no other thread runs: :func:`runner.offload.can_fork`)."""

    def __init__(self) -> None:
        self._held: dict[Path, float] = {}  # lock file -> its lease
        self._changed = threading.Condition()
        self._thread: threading.Thread | None = None
        self._ended: threading.Thread | None = None  # the thread that ended with the last lock

    def hold(self, path: Path, lease_s: float) -> None:
        with self._changed:
            self._held[path] = lease_s
            if self._thread is None:
                self._thread = threading.Thread(target=self._beat, name="lock-heartbeat", daemon=True)
                self._thread.start()
            self._changed.notify_all()

    def release(self, path: Path) -> None:
        with self._changed:
            self._held.pop(path, None)
            self._changed.notify_all()
            self._changed.wait_for(lambda: self._thread is None or bool(self._held))
            ended, self._ended = self._ended, None
        if ended is not None:
            ended.join()  # gone when the last lock is: a fork right after finds no other thread

    def _beat(self) -> None:
        with self._changed:
            while self._held:
                self._changed.wait(timeout=min(self._held.values()) / 4)
                for path in list(self._held):
                    try:
                        os.utime(path)
                    except OSError:
                        pass
            self._thread, self._ended = None, threading.current_thread()
            self._changed.notify_all()


_heartbeat = _Heartbeat()


class CacheStore:
    def __init__(self, root: Path, *, lease_s: float | None = None):
        self.root = Path(root)
        self.lease_s = lease_seconds() if lease_s is None else lease_s
        self.entries_dir = self.root / "entries"
        self.tmp_dir = self.root / "tmp"
        self.locks_dir = self.root / "locks"
        self.published_dir = self.root / "published"  # stat records of files published to --out (runner.publish)
        self.libraries_dir = self.root / "libraries"  # files the libraries the stages call keep (keep_library_files)
        self._me = {"pid": os.getpid(), "host": socket.gethostname(), "started": _process_start(os.getpid())}

    def keep_library_files(self) -> None:
        """Point the libraries that keep files of their own under ``$HOME`` at
        :attr:`libraries_dir`, so that a run writes only under ``--out`` and its cache:
        matplotlib's font cache and configuration (``MPLCONFIGDIR``, read when matplotlib is
        first imported). A folder the user set is kept."""
        os.environ.setdefault("MPLCONFIGDIR", str((self.libraries_dir / "matplotlib").resolve()))

    # -- entries ---------------------------------------------------------------------------

    def entry_path(self, key: str) -> Path:
        return self.entries_dir / key[:2] / key

    def lookup(self, key: str) -> Entry | None:
        """The complete entry for ``key``, or None."""
        path = self.entry_path(key)
        try:
            record = json.loads((path / COMPLETE).read_text())
        except (OSError, ValueError):
            return None
        return Entry(key, path, record)

    @contextmanager
    def writing(self, key: str) -> Iterator[Path]:
        """A fresh temporary folder to write the entry ``key`` into; removed on exit unless
        :meth:`commit` moved it into place."""
        self.tmp_dir.mkdir(parents=True, exist_ok=True)
        tmp = self.tmp_dir / f"{key}.{os.getpid()}.{secrets.token_hex(4)}"
        tmp.mkdir()
        try:
            yield tmp
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    def commit(self, key: str, tmp: Path, record: dict[str, Any], *, replace: bool = False) -> Entry:
        """Write the completion record into ``tmp`` and move it to the entry's place.

        With ``replace`` an existing entry is swapped out (``--force``); otherwise an entry
        committed meanwhile by another process wins and ``tmp`` is dropped.
        """
        record = {**record, "key": key, "created": time.time(), "pid": os.getpid()}
        try:
            (tmp / COMPLETE).write_text(json.dumps(record, indent=1, sort_keys=True))
        except OSError as exc:  # disk full: name the file
            raise OSError(exc.errno, exc.strerror, str(tmp / COMPLETE)) from exc
        final = self.entry_path(key)
        final.parent.mkdir(parents=True, exist_ok=True)
        # Replace the entry when asked (--force) or when what is there is no complete entry (a
        # folder whose completion record was damaged).
        if final.exists() and (replace or self.lookup(key) is None):
            self._remove_folder(key, final)
        try:
            os.replace(tmp, final)
        except OSError as exc:
            if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                raise
        entry = self.lookup(key)
        if entry is None:
            raise OSError(f"cache entry {final} vanished while being committed")
        return entry

    def touch(self, entry: Entry) -> None:
        """Record a use of ``entry`` (its folder's mtime), which ``gc --older-than`` reads."""
        try:
            os.utime(entry.path)
        except OSError:
            pass

    def iter_entries(self) -> Iterator[Entry]:
        if not self.entries_dir.is_dir():
            return
        for shard in sorted(self.entries_dir.iterdir()):
            for path in sorted(shard.iterdir()):
                entry = self.lookup(path.name)
                if entry is not None:
                    yield entry

    # -- locks -----------------------------------------------------------------------------

    @contextmanager
    def locked(self, key: str, *, on_wait: Callable[[dict[str, Any]], None] | None = None) -> Iterator[None]:
        """Hold the lock of entry ``key``; waits while a live process holds it, breaks it if
        its holder is dead. ``on_wait(holder)`` is called once when waiting starts."""
        self.locks_dir.mkdir(parents=True, exist_ok=True)
        path = self.locks_dir / f"{key}.lock"
        mine = json.dumps({**self._me, "time": time.time(), "token": secrets.token_hex(8)})
        waited = False
        seen: tuple[Any, float] | None = None  # the lock's (state, monotonic time it was first seen in)
        while True:
            tmp = path.with_name(f"{path.name}.{os.getpid()}.{secrets.token_hex(4)}")
            tmp.write_text(mine)
            try:
                os.link(tmp, path)
                break
            except FileExistsError:
                pass
            finally:
                tmp.unlink()
            holder = self._read_lock(path)
            state = _lock_state(path)
            if seen is None or seen[0] != state:
                seen = (state, time.monotonic())
            expired = time.monotonic() - seen[1] >= self.lease_s  # no heartbeat for a whole lease
            if holder is not None and (holder_is_stale(holder) or expired):
                self._break(path, holder)
                continue
            if not waited and on_wait is not None and holder is not None:
                on_wait(holder)
            waited = True
            time.sleep(POLL_S)
        _heartbeat.hold(path, self.lease_s)
        try:
            yield
        finally:
            _heartbeat.release(path)
            try:
                if path.read_text() == mine:
                    path.unlink()
            except OSError:
                pass

    @staticmethod
    def _read_lock(path: Path) -> dict[str, Any] | None:
        try:
            holder: dict[str, Any] = json.loads(path.read_text())
            return holder
        except (OSError, ValueError):
            return None

    def _break(self, path: Path, holder: dict[str, Any]) -> None:
        """Remove a stale lock, unless someone replaced it meanwhile."""
        with open(self.locks_dir / ".break", "a") as guard:
            fcntl.flock(guard, fcntl.LOCK_EX)
            if self._read_lock(path) == holder:
                path.unlink(missing_ok=True)

    def locks(self) -> list[tuple[Path, dict[str, Any] | None]]:
        if not self.locks_dir.is_dir():
            return []
        return [(p, self._read_lock(p)) for p in sorted(self.locks_dir.glob("*.lock"))]

    def break_stale_locks(self) -> int:
        """Remove the locks whose holder is gone from this host; how many. A process killed
        between an entry's commit and its lock's removal leaves a lock that no run wants again
        (the entry is complete), so :meth:`locked` alone would never break it."""
        stale = [(path, holder) for path, holder in self.locks() if holder is not None and holder_is_stale(holder)]
        for path, holder in stale:
            self._break(path, holder)
        return len(stale)

    # -- maintenance -----------------------------------------------------------------------

    def gc(self, *, older_than_s: float | None = None) -> dict[str, int]:
        """Remove what no live process needs: temporary folders and locks of dead processes,
        and, with ``older_than_s``, complete entries not used for that long.

        Returns counts ``{"tmp": n, "locks": n, "entries": n, "bytes": n}``.
        """
        counts = {"tmp": 0, "locks": 0, "entries": 0, "bytes": 0}
        if self.tmp_dir.is_dir():
            host = socket.gethostname()
            for tmp in self.tmp_dir.iterdir():
                pid = tmp.name.split(".")[1] if tmp.name.count(".") >= 2 else "-1"
                if holder_is_stale({"pid": int(pid) if pid.isdigit() else -1, "host": host}):
                    counts["bytes"] += _size(tmp)
                    shutil.rmtree(tmp, ignore_errors=True)
                    counts["tmp"] += 1
        counts["locks"] = self.break_stale_locks()
        if older_than_s is not None:
            limit = time.time() - older_than_s
            for entry in list(self.iter_entries()):
                if entry.path.stat().st_mtime < limit:
                    counts["bytes"] += _size(entry.path)
                    self.discard(entry)
                    counts["entries"] += 1
        return counts

    def clear(self) -> dict[str, int]:
        """Remove every entry and temporary folder (locks of live runs are left alone)."""
        counts = {"entries": 0, "bytes": 0}
        for entry in list(self.iter_entries()):
            counts["bytes"] += _size(entry.path)
            self.discard(entry)
            counts["entries"] += 1
        counts["tmp"] = self.gc()["tmp"]
        if self.entries_dir.is_dir():
            shutil.rmtree(self.entries_dir, ignore_errors=True)
        return counts

    def discard(self, entry: Entry) -> None:
        """Remove an entry (damaged, or collected): rename it away first, so that it vanishes
        atomically, then delete it."""
        self._remove_folder(entry.key, entry.path)

    def _remove_folder(self, key: str, path: Path) -> None:
        self.tmp_dir.mkdir(parents=True, exist_ok=True)
        gone = self.tmp_dir / f"{key}.{os.getpid()}.{secrets.token_hex(4)}.old"
        try:
            os.replace(path, gone)
        except OSError:
            return
        shutil.rmtree(gone, ignore_errors=True)


def _lock_state(path: Path) -> tuple[int, bytes] | None:
    """What a heartbeat changes: the lock file's mtime (ns) and its bytes; None if it is gone."""
    try:
        with open(path, "rb") as f:
            return os.fstat(f.fileno()).st_mtime_ns, f.read()
    except OSError:
        return None


def _size(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
