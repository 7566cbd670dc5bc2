"""A run killed with SIGKILL and started again finishes, recomputes only what was incomplete, and
publishes outputs byte-identical to an uninterrupted run's; concurrent runs share one cache."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import time
from pathlib import Path

import pytest

from runner.cache import CacheStore
from tests.runner.helpers import DATA, cli_env, read_log, run_cli, runner_cmd, stage_status, tree_bytes

pytestmark = [pytest.mark.subprocess]

GRAPH = DATA / "graph.yaml"
PUBLISHED = ("write", "table")


@pytest.fixture(scope="module")
def reference(plugin_site: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[str, bytes]]:
    """Published outputs of an uninterrupted run."""
    work = tmp_path_factory.mktemp("reference")
    done = run_cli("run", GRAPH, "--out", work / "out", env=cli_env(plugin_site, work / "cache"), cwd=work)
    assert done.returncode == 0, done.stderr
    return {stage: tree_bytes(work / "out" / stage) for stage in PUBLISHED}


def _wait_for(log: Path, proc: subprocess.Popen, condition, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if log.exists() and condition(read_log(log)):
            return
        assert proc.poll() is None, "the run ended before the kill point"
        time.sleep(0.01)
    raise AssertionError("kill point not reached")


def _ran_chunks(events, stage: str) -> set[tuple[int, int]]:
    return {(e["start"], e["stop"]) for e in events if e.get("event") == "chunk" and e["stage"] == stage and e["status"] == "ran"}


def _stored_chunks(cache: Path) -> dict[str, set[tuple[int, int]]]:
    """Chunk ranges of `add` and `gray` with a complete entry in the cache."""
    stored: dict[str, set[tuple[int, int]]] = {"add": set(), "gray": set()}
    for entry in CacheStore(cache).iter_entries():
        if entry.record.get("stage") in stored and "range" in entry.record:
            stored[entry.record["stage"]].add(tuple(entry.record["range"]))
    return stored


def _kill_then_resume(env, tmp_path, reference, *, wait, **slow: str) -> tuple[list, list, dict]:
    out, killed_log, resumed_log = tmp_path / "out", tmp_path / "killed.jsonl", tmp_path / "resumed.jsonl"
    proc = subprocess.Popen(
        runner_cmd("run", GRAPH, "--out", out, "--log-json", killed_log),
        env={**env, **slow},
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        wait(proc, killed_log)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    killed = read_log(killed_log) if killed_log.exists() else []
    stored = _stored_chunks(Path(env["RUNNER_CACHE_DIR"]))
    # Nothing published by the killed run looks complete unless it is.
    for stage in PUBLISHED:
        if (out / stage / "manifest.json").exists():
            assert tree_bytes(out / stage) == reference[stage]
    done = run_cli("run", GRAPH, "--out", out, "--log-json", resumed_log, env=env, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    resumed = read_log(resumed_log)
    for stage in PUBLISHED:
        assert tree_bytes(out / stage) == reference[stage]
    # Work completed before the kill (stored; the log may miss the last chunk stored) is not
    # redone; the rest is done once.
    for stage in ("add", "gray"):
        after = _ran_chunks(resumed, stage)
        assert _ran_chunks(killed, stage) <= stored[stage] and not stored[stage] & after
        assert stored[stage] | after == {(s, min(s + 8, 48)) for s in range(0, 48, 8)}
    for stage, status in stage_status(killed).items():
        if status in ("ran", "cached", "partial") and stage not in ("add", "gray"):
            assert stage_status(resumed)[stage] == "cached"
    return killed, resumed, stored


def test_kill_mid_chunk(env, tmp_path, reference):
    def wait(proc, log):  # two chunks of `add` done, the third sleeping
        _wait_for(log, proc, lambda events: len(_ran_chunks(events, "add")) >= 2)
        time.sleep(0.1)

    _, resumed, stored = _kill_then_resume(env, tmp_path, reference, wait=wait, RUNNER_TEST_SLEEP="0.4")
    assert len(stored["add"]) >= 2 and len(_ran_chunks(resumed, "add")) == 6 - len(stored["add"])
    # A dry run after a kill says what is left; here the resumed run already finished.
    dry = run_cli("run", GRAPH, "--out", tmp_path / "out", "--dry-run", env=env, cwd=tmp_path)
    assert "will run" not in dry.stdout


def test_dry_run_after_kill_names_missing_chunks(env, tmp_path):
    log = tmp_path / "killed.jsonl"
    proc = subprocess.Popen(
        runner_cmd("run", GRAPH, "--out", tmp_path / "out", "--log-json", log),
        env={**env, "RUNNER_TEST_SLEEP": "0.4"},
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        _wait_for(log, proc, lambda events: len(_ran_chunks(events, "add")) >= 1)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    done_chunks = len(_stored_chunks(Path(env["RUNNER_CACHE_DIR"]))["add"])
    dry = run_cli("run", GRAPH, "--out", tmp_path / "out", "--dry-run", env=env, cwd=tmp_path)
    add = next(line for line in dry.stdout.splitlines() if line.startswith("add"))
    assert f"{6 - done_chunks} of 6 chunks missing" in add


def test_kill_mid_write(env, tmp_path, reference):
    """write streams from gray, which streams from add: killed inside the encoder, the entries of
    the chunks of add and gray computed so far are stored (their frames are not) and the rest
    were never computed; the resumed run encodes the video again, computing the missing chunks
    and the frames of the stored ones again (``recompute`` events), and no entry twice."""

    def wait(proc, log):  # inside the encoder, some chunks written, the file not finished
        _wait_for(
            log,
            proc,
            lambda events: (
                len(_ran_chunks(events, "gray")) >= 2
                and any(e.get("event") == "stage_start" and e["stage"] == "write" for e in events)
            ),
        )
        time.sleep(0.2)

    # add is slowed down so that its producer threads (one per core, up to keep = 5 chunks ahead
    # of gray) have not computed its 6 chunks when the kill lands.
    killed, resumed, _ = _kill_then_resume(
        env, tmp_path, reference, wait=wait, RUNNER_TEST_SLEEP="0.5", RUNNER_TEST_WRITE_SLEEP="0.2"
    )
    assert "write" not in stage_status(killed)
    # Streaming: the writer was reading before its upstream stages had computed every chunk.
    assert 2 <= len(_ran_chunks(killed, "gray")) < 6 and len(_ran_chunks(killed, "add")) < 6
    status = stage_status(resumed)
    assert {stage: status[stage] for stage in ("decode", "add", "gray", "write")} == {
        "decode": "on demand",
        "add": "partial",
        "gray": "partial",
        "write": "ran",
    }
    again = {(e["start"], e["stop"]) for e in resumed if e.get("event") == "recompute" and e["stage"] == "gray"}
    assert again == _stored_chunks(Path(env["RUNNER_CACHE_DIR"]))["gray"] - _ran_chunks(resumed, "gray")


@pytest.mark.parametrize("computed", [1, 6, 11])
def test_kill_after_observed_chunks(env, tmp_path, reference, computed):
    """Killed once ``computed`` of the 12 chunks of add and gray were logged as computed (early,
    midway, near the end), so that the kill always lands inside the work."""

    def wait(proc, log):
        _wait_for(log, proc, lambda events: len(_ran_chunks(events, "add")) + len(_ran_chunks(events, "gray")) >= computed)

    killed, _, stored = _kill_then_resume(
        env, tmp_path, reference, wait=wait, RUNNER_TEST_SLEEP="0.1", RUNNER_TEST_WRITE_SLEEP="0.05"
    )
    assert len(stored["add"]) + len(stored["gray"]) >= computed


def test_stale_lock_of_killed_run_is_broken(env, tmp_path, reference):
    """A run killed while holding a chunk lock leaves it behind; the next run takes it over."""

    def wait(proc, log):
        _wait_for(log, proc, lambda events: len(_ran_chunks(events, "add")) >= 1)

    cache = Path(env["RUNNER_CACHE_DIR"])
    out, log = tmp_path / "out", tmp_path / "killed.jsonl"
    proc = subprocess.Popen(
        runner_cmd("run", GRAPH, "--out", out, "--log-json", log),
        env={**env, "RUNNER_TEST_SLEEP": "0.5"},
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        wait(proc, log)
        deadline = time.monotonic() + 10  # the next chunk's lock is taken just after the event
        while not list((cache / "locks").glob("*.lock")) and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert list((cache / "locks").glob("*.lock")), "the killed run held a lock"
    done = run_cli("run", GRAPH, "--out", out, env=env, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert tree_bytes(out / "write") == reference["write"]
    assert not list((cache / "locks").glob("*.lock"))
    gc = run_cli("cache", "gc", env=env, cwd=tmp_path)
    assert "temporary folders" in gc.stdout
    assert not any(p.name.split(".")[1] == str(proc.pid) for p in (cache / "tmp").iterdir())


def test_run_breaks_stale_locks_of_complete_entries(env, tmp_path, reference):
    """A process killed between an entry's commit and its lock's removal leaves a lock that no run
    wants again (the entry is complete): the next run that ends removes it, and leaves the lock
    of a live process alone."""
    out, cache = tmp_path / "out", Path(env["RUNNER_CACHE_DIR"])
    assert run_cli("run", GRAPH, "--out", out, env=env, cwd=tmp_path).returncode == 0
    store = CacheStore(cache)
    complete = [entry.key for entry in store.iter_entries()][:2]
    gone = subprocess.Popen(["true"])
    gone.wait()
    holders = {
        complete[0]: {"pid": gone.pid, "host": socket.gethostname(), "started": None},
        complete[1]: {"pid": os.getpid(), "host": socket.gethostname(), "started": None},
    }
    for key, holder in holders.items():
        (store.locks_dir / f"{key}.lock").write_text(json.dumps(holder))
    done = run_cli("run", GRAPH, "--out", out, env=env, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert tree_bytes(out / "write") == reference["write"]
    assert [path.stem for path, _ in store.locks()] == [complete[1]]


def test_two_concurrent_runs_share_the_cache(env, tmp_path, reference):
    out = tmp_path / "out"
    logs = [tmp_path / f"{i}.jsonl" for i in range(2)]
    procs = [
        subprocess.Popen(
            runner_cmd("run", GRAPH, "--out", out, "--log-json", log, "--jobs", str(i + 1)),
            env={**env, "RUNNER_TEST_SLEEP": "0.1"},
            cwd=tmp_path,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i, log in enumerate(logs)
    ]
    for proc in procs:
        _, err = proc.communicate(timeout=120)
        assert proc.returncode == 0, err
    for stage in PUBLISHED:
        assert tree_bytes(out / stage) == reference[stage]
    # Each chunk of `add` was computed by exactly one of the two runs.
    ran = [_ran_chunks(read_log(log), "add") for log in logs]
    assert not ran[0] & ran[1] and len(ran[0] | ran[1]) == 6
    assert not os.listdir(Path(env["RUNNER_CACHE_DIR"]) / "locks") or all(
        p.name == ".break" for p in (Path(env["RUNNER_CACHE_DIR"]) / "locks").iterdir()
    )


def test_second_interrupt_exits_at_once(env, tmp_path, reference):
    """The first signal stops the run cleanly, which waits for the chunks being computed (here
    30 s each); a second one ends the process at once, exit 130, and the next run completes."""
    log = tmp_path / "interrupted.jsonl"
    proc = subprocess.Popen(
        runner_cmd("run", GRAPH, "--out", tmp_path / "out", "--log-json", log),
        env={**env, "RUNNER_TEST_SLEEP": "30"},
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        _wait_for(log, proc, lambda events: any(e.get("event") == "stage_start" and e["stage"] == "add" for e in events))
        time.sleep(0.5)  # add's chunks are sleeping
        proc.send_signal(signal.SIGTERM)
        with pytest.raises(subprocess.TimeoutExpired):
            proc.wait(timeout=1.5)  # still stopping: waiting for the sleeping chunks
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=10)
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == 130 and "interrupted again: exiting now" in err
    done = run_cli("run", GRAPH, "--out", tmp_path / "out", env=env, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    for stage in PUBLISHED:
        assert tree_bytes(tmp_path / "out" / stage) == reference[stage]


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_interrupt_exits_130_and_resumes(env, tmp_path, reference, signum):
    log = tmp_path / "interrupted.jsonl"
    proc = subprocess.Popen(
        runner_cmd("run", GRAPH, "--out", tmp_path / "out", "--log-json", log),
        env={**env, "RUNNER_TEST_SLEEP": "0.3"},
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    _wait_for(log, proc, lambda events: len(_ran_chunks(events, "add")) >= 1)
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and err.strip() == "interrupted"
    assert read_log(log)[-1]["status"] == "interrupted"
    assert not list((Path(env["RUNNER_CACHE_DIR"]) / "locks").glob("*.lock"))  # released on the way out
    done = run_cli("run", GRAPH, "--out", tmp_path / "out", env=env, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    for stage in PUBLISHED:
        assert tree_bytes(tmp_path / "out" / stage) == reference[stage]
