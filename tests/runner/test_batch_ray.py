"""The local Ray of `runner batch` (runner.batch_ray): it runs tasks on the CPUs asked for, in
workers at the driver's priority (ray.init()'s are niced), without the dashboard head, the
autoscaler monitor and the log monitor that `ray.init()` starts (the same processes found in a
`ray.init()` Ray, so the check can fail), leaves no process running once stopped, and falls back
to `ray.init()` with a note when Ray's node API is missing.
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

import pytest
import ray

from runner.batch_ray import start_local_ray
from tests.runner.test_batch import TAG, _assert_gone, _tagged_pids

pytestmark = [pytest.mark.ray]

# Scripts of the Python processes a batch on one machine does not use.
UNUSED = {
    "dashboard head": "ray/dashboard/dashboard.py",
    "autoscaler monitor": "/monitor.py",
    "log monitor": "ray/_private/log_monitor.py",
}


def _started(tag: str, start) -> tuple[set[str], float, object]:
    """Start a Ray with ``start`` in an environment tagged ``tag``; returns which of
    :data:`UNUSED` run, the CPUs Ray reports and ``start``'s result."""
    os.environ[TAG] = tag
    try:
        result = start()
    finally:
        del os.environ[TAG]
    commands = set()
    for pid in _tagged_pids(tag) - {os.getpid()}:
        try:
            commands.add(Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode())
        except OSError:
            continue
    running = {name for name, script in UNUSED.items() if any(script in command for command in commands)}
    return running, ray.cluster_resources().get("CPU"), result


@ray.remote(num_cpus=1)
def _pid_and_nice() -> tuple[int, int]:
    return os.getpid(), os.getpriority(os.PRIO_PROCESS, 0)


@pytest.mark.subprocess
def test_local_ray_runs_tasks_without_the_unused_processes_and_stops_them_all():
    tag = f"batch-ray-{os.getpid()}"
    running, _, _ = _started(
        f"{tag}-init", lambda: ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
    )
    try:
        _, nice = ray.get(_pid_and_nice.remote())
    finally:
        ray.shutdown()
    assert running == set(UNUSED)  # what ray.init() starts, found by these patterns
    assert nice == min(19, os.getpriority(os.PRIO_PROCESS, 0) + 15)  # ray.init()'s workers are niced
    _assert_gone(f"{tag}-init")

    notes = []
    running, cpus, stop = _started(tag, lambda: start_local_ray(3, note=notes.append))
    try:
        assert running == set() and cpus == 3 and not notes
        pid, nice = ray.get(_pid_and_nice.remote())
        assert pid in _tagged_pids(tag)  # a worker of this Ray
        assert nice == os.getpriority(os.PRIO_PROCESS, 0)  # at the driver's priority, as `runner run` computes
    finally:
        stop()
    assert not ray.is_initialized()
    _assert_gone(tag)


def test_missing_node_api_falls_back_to_ray_init_with_a_note(monkeypatch):
    calls = []
    monkeypatch.setitem(sys.modules, "ray._private.parameter", None)  # `from ... import RayParams` fails
    monkeypatch.setattr(ray, "init", lambda **kwargs: calls.append(kwargs))
    notes = []
    stop = start_local_ray(2, note=notes.append)
    assert stop is ray.shutdown and len(notes) == 1 and "ray.init()" in notes[0]
    assert calls == [
        {"address": "local", "num_cpus": 2, "include_dashboard": False, "log_to_driver": False, "logging_level": logging.ERROR}
    ]


@pytest.mark.parametrize("cpus", [0, -1, 1.5, True, "2"])
def test_cpus_must_be_a_positive_int(cpus):
    with pytest.raises(ValueError, match=f"cpus must be a positive int, got {cpus!r}"):
        start_local_ray(cpus, note=print)
