"""`runner batch --address` on a Ray cluster of three nodes on this machine (`ray start`
processes of their own, as on three hosts) sharing one cache folder: jobs on nodes of two
host names share the cache's locks, two batches at once share the cache, and a node killed
mid-batch (its raylet and workers) has its job retried on another node; the outputs are always
byte-identical to `runner run`'s.

The nodes: the head (no CPU for jobs: the GCS and the drivers' node), node ``a`` (1 CPU) and
node ``b`` (1 CPU) in a UTS namespace of its own whose host name is ``other-node`` (``unshare
--uts``), so that its processes' locks name another host: judged by their heartbeat, not by
PID. Locks use a short lease here (``RUNNER_LOCK_LEASE_S``) so that a killed node's lock is
broken within seconds. Ray's files go to a temporary folder of the module's (the head's
``--temp-dir``): no other Ray on the machine connects to this cluster by mistake. No process of
the cluster is left running (checked).
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import pytest

from tests.runner.helpers import read_log, runner_cmd, tree_bytes
from tests.runner.test_batch import TAG, TWO_JOBS, _assert_gone, _env, _manifest, _tagged_pids, alone, site  # noqa: F401 - fixtures (alone, site) shared with test_batch: pytest finds them by name here

pytestmark = [pytest.mark.slow, pytest.mark.ray, pytest.mark.subprocess]

NODE = "RUNNER_BATCH_TEST_NODE"  # which node a Ray process belongs to (in its environment)
RAY = Path(sys.executable).with_name("ray")
LEASE_S = "3"
OTHER_HOST = "other-node"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _node_pids(tag: str, node: str) -> set[int]:
    return {pid for pid in _tagged_pids(tag) if f"{NODE}={node}".encode() in _environ(pid)}


def _environ(pid: int) -> list[bytes]:
    try:
        return Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    except OSError:
        return []


def _node_of(pid: int) -> str | None:
    return next((v.split(b"=", 1)[1].decode() for v in _environ(pid) if v.startswith(f"{NODE}=".encode())), None)


def _alive_nodes(address: str, env: dict[str, str]) -> int:
    probe = (
        "import ray, logging; ray.init(address=%r, log_to_driver=False, logging_level=logging.ERROR); "
        "print(sum(n['Alive'] for n in ray.nodes()))" % address
    )
    done = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, timeout=120)
    return int(done.stdout.strip() or 0)


@pytest.fixture(scope="module")
def cluster(site: str) -> dict[str, Any]:  # noqa: F811 - the fixture imported above
    tag = f"three-nodes-{os.getpid()}"
    temp = Path(tempfile.mkdtemp(prefix="rc-", dir="/tmp"))  # short: Ray's socket paths have a limit
    port = _free_port()
    address = f"127.0.0.1:{port}"
    env = {
        **os.environ,
        "PYTHONPATH": site,
        "RUNNER_TEST_SLEEP": "0.3",
        "RUNNER_LOCK_LEASE_S": LEASE_S,
        "RAY_AUTH_MODE": "token",
        "RAY_USAGE_STATS_ENABLED": "0",
        TAG: tag,
    }
    common = ["--object-store-memory", str(100 * 2**20), "--disable-usage-stats"]
    starts = [
        (
            "head",
            [
                str(RAY),
                "start",
                "--head",
                "--port",
                str(port),
                "--num-cpus",
                "0",
                "--include-dashboard",
                "false",
                "--temp-dir",
                str(temp),
                *common,
            ],
        ),
        ("a", [str(RAY), "start", "--address", address, "--num-cpus", "1", *common]),
        (
            "b",
            [
                "unshare",
                "--uts",
                "sh",
                "-c",
                f'hostname {OTHER_HOST} && exec "$@"',
                "sh",
                str(RAY),
                "start",
                "--address",
                address,
                "--num-cpus",
                "1",
                *common,
            ],
        ),
    ]
    try:
        for name, command in starts:
            done = subprocess.run(command, env={**env, NODE: name}, capture_output=True, text=True, timeout=180)
            assert done.returncode == 0, f"node {name}: {done.stderr[-2000:]}"
        deadline = time.monotonic() + 120
        while _alive_nodes(address, env) < 3:
            assert time.monotonic() < deadline, "the three nodes did not all join"
            time.sleep(1)
        yield {"address": address, "tag": tag, "env": env}
    finally:
        for pid in _tagged_pids(tag) - {os.getpid()}:
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
        _assert_gone(tag)
        shutil.rmtree(temp, ignore_errors=True)


def _driver_env(site: str, tmp_path: Path) -> dict[str, str]:  # noqa: F811 - `site` and `alone` are the fixtures imported above
    return {**_env(site, tmp_path), "RUNNER_LOCK_LEASE_S": LEASE_S}


def _ran_chunks(events: list[dict[str, Any]], job: str) -> list[int]:
    return sorted(
        e["start"]
        for e in events
        if e.get("event") == "chunk" and e.get("job") == job and e["stage"] == "add" and e["status"] == "ran"
    )


def _job_starts(events: list[dict[str, Any]], job: str) -> list[dict[str, Any]]:
    return [e for e in events if e.get("event") == "job_start" and e["job"] == job]


ADD_CHUNKS = [0, 8, 16, 24, 32, 40]  # test.add's chunks of the 48-frame clip, 8 frames each


def test_jobs_on_nodes_of_two_host_names_share_the_locks(site, cluster, alone, tmp_path):  # noqa: F811 - `site` and `alone` are the fixtures imported above
    """Two jobs of the same shot at once, one on each 1-CPU node: one on this host, one on
    ``other-node``; each chunk is computed once (one job waits for the other's lock, judged by
    its heartbeat across the hosts), both outputs are `runner run`'s."""
    shot = TWO_JOBS["plus10"]
    path = _manifest(tmp_path, {"here": dict(shot), "there": dict(shot)})
    log = tmp_path / "log.jsonl"
    done = subprocess.run(
        runner_cmd("batch", path, "--address", cluster["address"], "--log-json", log),
        env=_driver_env(site, tmp_path),
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    events = read_log(log)
    hosts = {e["host"] for job in ("here", "there") for e in _job_starts(events, job)}
    assert hosts == {socket.gethostname(), OTHER_HOST}
    assert sorted(_ran_chunks(events, "here") + _ran_chunks(events, "there")) == ADD_CHUNKS
    for job in ("here", "there"):
        assert tree_bytes(tmp_path / "out" / job) == alone["plus10"]


def test_two_batches_at_once_share_the_cache(site, cluster, alone, tmp_path):  # noqa: F811 - `site` and `alone` are the fixtures imported above
    """Two `runner batch` drivers at once on the same cache, each with both shots (into their
    own folders): every chunk of a shot is computed by one of them only, and every output is
    `runner run`'s."""
    runs = {}
    for name in ("first", "second"):
        folder = tmp_path / name
        folder.mkdir()
        jobs = {job: {**spec, "out": str(folder / "out" / job)} for job, spec in TWO_JOBS.items()}
        log = folder / "log.jsonl"
        runs[name] = (
            log,
            subprocess.Popen(
                runner_cmd("batch", _manifest(folder, jobs), "--address", cluster["address"], "--log-json", log),
                env=_driver_env(site, tmp_path),
                cwd=folder,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE,
                text=True,
            ),
        )
    for log, process in runs.values():
        _, stderr = process.communicate(timeout=300)
        assert process.returncode == 0, stderr
    for job in TWO_JOBS:
        computed = [chunk for log, _ in runs.values() for chunk in _ran_chunks(read_log(log), job)]
        assert sorted(computed) == ADD_CHUNKS
        for name in runs:
            assert tree_bytes(tmp_path / name / "out" / job) == alone[job]


def test_a_node_killed_mid_batch_has_its_job_retried_on_another(site, cluster, alone, tmp_path):  # noqa: F811 - `site` and `alone` are the fixtures imported above
    """Once a job has committed a chunk on a worker node, that node is killed (its raylet, its
    workers and agents: SIGKILL): Ray retries the job on the other node, which breaks the killed
    job's lock (its heartbeat stopped) and resumes from the cache: the outputs are `runner
    run`'s. Last in the module: the node stays dead."""
    path = _manifest(tmp_path, TWO_JOBS)
    log = tmp_path / "log.jsonl"
    process = subprocess.Popen(
        runner_cmd("batch", path, "--address", cluster["address"], "--log-json", log),
        env=_driver_env(site, tmp_path),
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 180
        victim = None
        while victim is None:
            assert process.poll() is None and time.monotonic() < deadline, "no chunk was committed on a worker node"
            time.sleep(0.05)
            events = read_log(log) if log.exists() else []
            for job in TWO_JOBS:
                starts = _job_starts(events, job)
                if starts and _ran_chunks(events, job):
                    victim = (job, _node_of(starts[-1]["pid"]))
                    break
        job, node = victim
        assert node in ("a", "b")
        killed = _node_pids(cluster["tag"], node)
        for pid in killed:
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
        _, stderr = process.communicate(timeout=300)
    finally:
        process.kill()
        process.wait()
    assert process.returncode == 0, stderr
    events = read_log(log)
    starts = _job_starts(events, job)
    assert len(starts) >= 2 and starts[0]["pid"] in killed and starts[-1]["pid"] not in killed
    for name in TWO_JOBS:
        assert tree_bytes(tmp_path / "out" / name) == alone[name]
    assert events[-1]["event"] == "batch_end" and events[-1]["done"] == 2
