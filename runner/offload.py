"""Sequence stages that read a clip's frames, computed in a child process beside the run.

The stages before a run's streamed section are Python-heavy (tracking's per-point loop, pose,
importing torch for the target's model): on threads of one process they take turns on the GIL
and gain nothing (docs/runner.md, "End-to-end speed"). So when a sequence stage that reads the
frames of a source (``video.decode``: a tracker, a landmarker) is ready while another stage is
ready too, the runner starts a child process that runs the pipeline up to that stage and the
sequence stages after it that read nothing else the run has still to compute (the performer's
smoothing, compensation and pose: ``Runner`` with ``until``), against the same cache, inputs,
parameters and device, and goes on with the other stages meanwhile. The child is a fork of the
run where that is safe (:func:`can_fork`: no other thread and no torch, OpenCV, Ray... loaded
yet, as at a run's start), else a new interpreter (:func:`start`, running :func:`runner.child.main`). The
child commits the stages' entries as the run would (the cache's locks and atomic commits hold across processes, as
for ``runner batch``); once it has ended, the run visits those stages and finds their entries. A
child that fails leaves what it committed: the run computes the rest itself and reports its error
as usual. The child's events come to the run on the child's standard output, one JSON object a
line: the run logs each as a ``child`` event, shows its warnings, logs its stages' log records
again (a stage's ``ctx.log.warning``, e.g. frames without a face) and takes each stage's seconds
from them. A child whose parent is gone (killed) stops within half a second; its cache is left
resumable.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any, NoReturn

import runner
from runner.signals import exit_now
from runner.stage import SUMMARY

SPEC_VERSION = 2


def spec(*, pipeline: Path, overrides: list[str], bound: dict[str, Path], cache: Path, device: str, stages: list[str]) -> str:
    """The child's command-line argument: what it needs to run ``pipeline`` up to ``stages`` as
    the parent would (JSON)."""
    return json.dumps(
        {
            "version": SPEC_VERSION,
            "pipeline": str(pipeline),
            "overrides": list(overrides),
            "bound": {name: str(path) for name, path in bound.items()},
            "cache": str(cache),
            "device": device,
            "until": list(stages),
        }
    )


def start(argument: str) -> subprocess.Popen[str]:
    """Start the child process for :func:`spec`'s ``argument``; its events are lines of its
    standard output (text), its standard error is dropped."""
    package_root = str(Path(runner.__file__).resolve().parent.parent)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [package_root, os.environ.get("PYTHONPATH")]))}
    return subprocess.Popen(
        [sys.executable, "-c", "from runner.child import main; main()", argument, str(os.getpid())],
        env=env,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        bufsize=1,
    )


class Forked:
    """A child made by :func:`fork`: what the run uses of :class:`subprocess.Popen` (``pid``,
    ``stdout`` lines, :meth:`wait`, :meth:`terminate`, ``returncode``)."""

    def __init__(self, pid: int, stdout: IO[str]):
        self.pid, self.stdout = pid, stdout
        self.returncode: int | None = None
        self._lock = threading.Lock()

    def wait(self) -> int:
        with self._lock:  # the relay thread and an interrupted run may both wait
            if self.returncode is None:
                _, status = os.waitpid(self.pid, 0)
                self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def terminate(self) -> None:
        if self.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signal.SIGTERM)


# Libraries whose native threads or runtimes do not survive a fork (a lock held by one of their
# threads stays held in the child; gRPC, OpenMP and CUDA state are per process).
FORK_UNSAFE = ("torch", "cv2", "ray", "grpc", "mediapipe", "tensorflow", "jax")


def can_fork() -> bool:
    """Whether :func:`fork` may fork now: ``os.fork`` exists, no other Python thread runs, and no
    library of :data:`FORK_UNSAFE` is loaded (at a run's start none is: the stages import them
    when they run)."""
    return hasattr(os, "fork") and threading.active_count() == 1 and not any(name in sys.modules for name in FORK_UNSAFE)


def fork(make_runner: Callable[..., Any]) -> Forked | None:
    """Start the child by forking this process, which has imported the runner, NumPy and the
    clip's decoder already and has loaded the pipeline (a new interpreter took 0.5-0.6 s to get
    there, on the run's longest path before the stream). The child runs
    ``make_runner(log=..., warn=...).run()`` with its events on a pipe. None where a fork is not
    safe (:func:`can_fork`); the run then uses :func:`start`."""
    if not can_fork():
        return None
    read, write = os.pipe()
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid == 0:  # the child: never returns
        os.close(read)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        devnull = os.open(os.devnull, os.O_RDWR)
        os.dup2(devnull, 0)
        os.dup2(devnull, 2)
        global _events
        _events = os.fdopen(write, "w")
        run_child(make_runner, parent=os.getppid())
    os.close(write)
    return Forked(pid, os.fdopen(read, "r"))


_events: IO[str] = sys.stdout  # where the child writes its events (a forked child: its pipe)


def _event_line(event: dict[str, Any]) -> None:
    """Write one event of the child's run for the parent, one JSON object a line."""
    _events.write(json.dumps(event, default=str) + "\n")
    _events.flush()


class _LogEvents(logging.Handler):
    """The child's log records (a stage's ``ctx.log.warning``) as ``log`` events, which the
    parent logs again on the same logger."""

    def emit(self, record: logging.LogRecord) -> None:
        _event_line({"event": "log", "logger": record.name, "level": record.levelno, "message": record.getMessage()})


def _exit_when_orphaned(parent: int) -> None:
    """End this process once ``parent`` is no longer its parent (the run was killed)."""
    while os.getppid() == parent:
        time.sleep(0.5)
    os._exit(1)


def run_child(make_runner: Callable[..., Any], *, parent: int) -> NoReturn:
    """The child's run, either way it started: events to the parent, exit 0 once its entries are
    committed, 1 on any failure (the parent then computes what is missing itself and reports
    why), without the interpreter's teardown (the run waits for this process's end; 0.2-0.3 s)."""
    from runner.notes import one_line_warnings

    threading.Thread(target=_exit_when_orphaned, args=(parent,), daemon=True).start()
    stage_log = logging.getLogger("runner.stage")  # its SUMMARY lines reach the parent too
    stage_log.setLevel(logging.INFO)
    logging.getLogger().addHandler(_LogEvents(SUMMARY))
    one_line_warnings()  # relayed as log events too
    code = 0
    try:
        make_runner(log=_event_line, warn=lambda line: _event_line({"event": "warning", "line": line})).run()
    except KeyboardInterrupt:
        code = 130
    except Exception:  # noqa: BLE001 - the parent computes the stages again and reports the error
        code = 1
    exit_now(code)
