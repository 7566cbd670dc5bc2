"""Cache store: whole-or-absent entries, locks with stale detection, maintenance, keys, digests."""

from __future__ import annotations

import hashlib
import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from runner.cache import CacheStore, holder_is_stale
from runner.digest import array_digest, bundle_digest, cache_key, canonical_json, library_versions, tree_digest


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_entry_is_absent_until_committed_and_tmp_is_cleaned(tmp_path):
    store = CacheStore(tmp_path)
    with store.writing("ab" * 32) as tmp:
        (tmp / "x.npy").write_bytes(b"data")
        assert store.lookup("ab" * 32) is None
        entry = store.commit("ab" * 32, tmp, {"stage": "s"})
    assert entry.record["stage"] == "s" and (entry.path / "x.npy").read_bytes() == b"data"
    assert store.lookup("ab" * 32).record["key"] == "ab" * 32
    with pytest.raises(RuntimeError):
        with store.writing("cd" * 32) as tmp:
            (tmp / "x.npy").write_bytes(b"partial")
            raise RuntimeError("killed")
    assert store.lookup("cd" * 32) is None and not list(store.tmp_dir.iterdir())
    # A folder without its completion record is not an entry.
    (store.entry_path("ef" * 32)).mkdir(parents=True)
    assert store.lookup("ef" * 32) is None
    assert [e.key for e in store.iter_entries()] == ["ab" * 32]


def test_second_commit_of_same_key_keeps_the_first_unless_replacing(tmp_path):
    store = CacheStore(tmp_path)
    for value, replace in (("first", False), ("second", False), ("third", True)):
        with store.writing("k" * 64) as tmp:
            (tmp / "v").write_text(value)
            entry = store.commit("k" * 64, tmp, {}, replace=replace)
        assert (entry.path / "v").read_text() == ("third" if replace else "first")


@pytest.mark.subprocess
def test_stale_lock_of_dead_process_is_broken(tmp_path):
    store = CacheStore(tmp_path)
    store.locks_dir.mkdir(parents=True)
    lock = store.locks_dir / f"{'a' * 64}.lock"
    dead = {"pid": _dead_pid(), "host": socket.gethostname(), "started": None}
    lock.write_text(json.dumps(dead))
    assert holder_is_stale(dead)
    assert not holder_is_stale({"pid": os.getpid(), "host": socket.gethostname(), "started": None})
    assert not holder_is_stale({"pid": dead["pid"], "host": "another-host", "started": None})
    # Same PID but a different process start time: the PID was reused, the lock is stale.
    assert holder_is_stale({"pid": os.getpid(), "host": socket.gethostname(), "started": -1})
    with store.locked("a" * 64):
        assert json.loads(lock.read_text())["pid"] == os.getpid()
    assert not lock.exists()


def test_live_lock_makes_others_wait(tmp_path):
    store = CacheStore(tmp_path)
    events = []
    holding, release = threading.Event(), threading.Event()

    def holder():
        with store.locked("b" * 64):
            events.append("holder in")
            holding.set()
            release.wait(10)
            events.append("holder out")

    thread = threading.Thread(target=holder)
    thread.start()
    holding.wait(10)
    waited = []
    other = CacheStore(tmp_path)

    def waiter():
        with other.locked("b" * 64, on_wait=waited.append):
            events.append("waiter in")

    second = threading.Thread(target=waiter)
    second.start()
    while not waited:
        time.sleep(0.01)
    release.set()
    thread.join()
    second.join()
    assert events == ["holder in", "holder out", "waiter in"]
    assert waited[0]["pid"] == os.getpid()


@pytest.mark.subprocess
def test_gc_removes_leftovers_of_dead_runs_and_old_entries(tmp_path):
    store = CacheStore(tmp_path)
    dead = _dead_pid()
    store.tmp_dir.mkdir(parents=True)
    (store.tmp_dir / f"{'c' * 64}.{dead}.abcd").mkdir()
    (store.tmp_dir / f"{'c' * 64}.{os.getpid()}.abcd").mkdir()
    store.locks_dir.mkdir()
    (store.locks_dir / "d.lock").write_text(json.dumps({"pid": dead, "host": socket.gethostname()}))
    with store.writing("e" * 64) as tmp:
        old = store.commit("e" * 64, tmp, {})
    os.utime(old.path, (time.time() - 10 * 86400,) * 2)
    with store.writing("f" * 64) as tmp:
        store.commit("f" * 64, tmp, {})
    counts = store.gc(older_than_s=86400)
    assert (counts["tmp"], counts["locks"], counts["entries"]) == (1, 1, 1)
    assert [p.name.split(".")[1] for p in store.tmp_dir.iterdir() if not p.name.endswith(".old")] == [str(os.getpid())]
    assert [e.key for e in store.iter_entries()] == ["f" * 64]
    assert store.clear()["entries"] == 1 and list(store.iter_entries()) == []


def test_keys_and_digests():
    base = {"stage": "s", "version": "1", "params": {"a": 1, "b": [1, 2]}, "inputs": {"x": "0" * 64}}
    assert cache_key(base) == hashlib.sha256(canonical_json(base).encode()).hexdigest()
    assert cache_key(dict(reversed(list(base.items())))) == cache_key(base)
    for change in ({"version": "2"}, {"params": {"a": 2, "b": [1, 2]}}, {"inputs": {"x": "1" * 64}}):
        assert cache_key({**base, **change}) != cache_key(base)
    versions = library_versions()
    assert versions["numpy"] == np.__version__ and "torch" in versions and "av" in versions
    a = np.arange(6, dtype=np.int32).reshape(2, 3)
    assert array_digest(a) == array_digest(a.copy(order="F"))
    assert array_digest(a) != array_digest(a.reshape(3, 2)) != array_digest(a.astype(np.int64))
    assert bundle_digest({"a": a, "b": a}) != bundle_digest({"a": a, "c": a})
    with pytest.raises(TypeError):
        array_digest(np.array([object()]))


def test_tree_digest_depends_on_names_and_bytes_only(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "x.txt").write_text("1")
    first = tree_digest(tmp_path)
    os.utime(tmp_path / "a" / "x.txt", (0, 0))
    assert tree_digest(tmp_path) == first
    (tmp_path / "a" / "x.txt").write_text("2")
    assert tree_digest(tmp_path) != first
    (tmp_path / "a" / "x.txt").write_text("1")
    (tmp_path / "a" / "x.txt").rename(tmp_path / "a" / "y.txt")
    assert tree_digest(tmp_path) != first


LEASE = 0.4  # s: short leases for the tests below


def _other_host_lock(store: CacheStore, key: str, *, wall_clock: float) -> Path:
    """A lock of a process on another host (a cluster node), stamped by a clock of its own."""
    store.locks_dir.mkdir(parents=True, exist_ok=True)
    lock = store.locks_dir / f"{key}.lock"
    lock.write_text(json.dumps({"pid": os.getpid(), "host": "other-node", "started": 1, "time": wall_clock}))
    return lock


def _take(store: CacheStore, key: str, taken: list[float]) -> threading.Thread:
    def take():
        with store.locked(key):
            taken.append(time.monotonic())

    thread = threading.Thread(target=take, daemon=True)
    thread.start()
    return thread


@pytest.mark.parametrize("clock_offset_s", [0.0, -86400.0, 86400.0])
def test_a_lock_of_another_host_is_broken_once_its_heartbeat_stops(tmp_path, clock_offset_s):
    """Another host's lock cannot be judged by its PID: while its file changes (the holder's
    heartbeat) it is waited for, and once it stayed unchanged for a lease it is broken (its host
    was killed), whatever that host's clock wrote in it: a day behind or ahead."""
    store = CacheStore(tmp_path, lease_s=LEASE)
    lock = _other_host_lock(store, "c" * 64, wall_clock=time.time() + clock_offset_s)
    taken: list[float] = []
    beating = time.monotonic() + 3 * LEASE
    thread = _take(store, "c" * 64, taken)
    while time.monotonic() < beating:  # the holder's heartbeat: the waiter keeps waiting
        time.sleep(LEASE / 8)
        assert not taken
        os.utime(lock)
        stopped = time.monotonic()
    thread.join(timeout=20)
    assert taken and LEASE <= taken[0] - stopped, "broken before a whole lease without a heartbeat"
    assert not lock.exists()


def test_a_held_lock_keeps_its_heartbeat(tmp_path):
    """A process holding a lock for several leases refreshes it: another process's waiter (a
    store with the same short lease) does not break it."""
    holder, waiter = CacheStore(tmp_path, lease_s=LEASE), CacheStore(tmp_path, lease_s=LEASE)
    events = []
    holding = threading.Event()

    def hold():
        with holder.locked("d" * 64):
            holding.set()
            time.sleep(4 * LEASE)
            events.append("released")

    first = threading.Thread(target=hold)
    first.start()
    holding.wait(10)
    lock = tmp_path / "locks" / f"{'d' * 64}.lock"
    record = json.loads(lock.read_text())
    lock.write_text(json.dumps({**record, "host": "other-node"}))  # judged by its heartbeat only
    taken: list[float] = []
    second = _take(waiter, "d" * 64, taken)
    first.join()
    second.join(timeout=20)
    assert events == ["released"] and taken
