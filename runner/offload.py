"""Sequence stages that read a clip's frames, computed in a child process beside the run.

The stages before a run's streamed section are Python-heavy (tracking's per-point loop, pose,
importing torch for the target's model): on threads of one process they take turns on the GIL
and gain nothing (docs/runner.md, "End-to-end speed"). So when a sequence stage that reads the
frames of a source (``video.decode``: a tracker, a landmarker) is ready while another stage is
ready too, the runner starts a child process that runs the pipeline up to that stage and the
sequence stages after it that read nothing else the run has still to compute (the performer's
smoothing, compensation and pose: ``Runner`` with ``until``), against the same cache, inputs,
parameters and device, and goes on with the other stages meanwhile. The child commits the
stages' entries as the run would (the cache's locks and atomic commits hold across processes, as
for ``runner batch``); once it has ended, the run visits those stages and finds their entries. A
child that fails leaves what it committed: the run computes the rest itself and reports its error
as usual. The child's events come to the run on the child's standard output, one JSON object a
line: the run logs each as a ``child`` event, shows its warnings, logs its stages' log records
again (a stage's ``ctx.log.warning``, e.g. frames without a face) and takes each stage's seconds
from them. A child whose parent is gone (killed) stops within half a second; its cache is left
resumable.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import runner

SPEC_VERSION = 2


def spec(*, pipeline: Path, overrides: list[str], bound: dict[str, Path], cache: Path, device: str,
         stages: list[str]) -> str:
    """The child's command-line argument: what it needs to run ``pipeline`` up to ``stages`` as
    the parent would (JSON)."""
    return json.dumps({"version": SPEC_VERSION, "pipeline": str(pipeline), "overrides": list(overrides),
                       "bound": {name: str(path) for name, path in bound.items()}, "cache": str(cache),
                       "device": device, "until": list(stages)})


def start(argument: str) -> subprocess.Popen:
    """Start the child process for :func:`spec`'s ``argument``; its events are lines of its
    standard output (text), its standard error is dropped."""
    package_root = str(Path(runner.__file__).resolve().parent.parent)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [package_root, os.environ.get("PYTHONPATH")]))}
    return subprocess.Popen([sys.executable, "-c", "from runner.offload import main; main()", argument, str(os.getpid())],
                            env=env, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            text=True, bufsize=1)


def _event_line(event: dict[str, Any]) -> None:
    """Write one event of the child's run to its standard output (read by the parent)."""
    sys.stdout.write(json.dumps(event, default=str) + "\n")
    sys.stdout.flush()


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


def main(argv: list[str] | None = None) -> None:
    """The child: run the pipeline up to the spec's stages against the shared cache, publishing
    nothing, its events on standard output; exit 0 once its entries are committed, 1 on any
    failure (the parent then computes what is missing itself and reports why)."""
    from runner.cache import CacheStore
    from runner.cli import exit_now
    from runner.config import load_pipeline
    from runner.execute import Options, Runner
    from runner.registry import Registry

    argument, parent = argv or sys.argv[1:]
    threading.Thread(target=_exit_when_orphaned, args=(int(parent),), daemon=True).start()
    args: dict[str, Any] = json.loads(argument)
    if args.get("version") != SPEC_VERSION:
        sys.exit(2)
    logging.getLogger().addHandler(_LogEvents(logging.WARNING))
    code = 0
    try:
        loaded = load_pipeline(Path(args["pipeline"]), Registry.from_entry_points(), overrides=args["overrides"])
        bound = {name: Path(path) for name, path in args["bound"].items()}
        options = Options(cache=CacheStore(Path(args["cache"])), device=args["device"], until=tuple(args["until"]),
                          log=_event_line, warn=lambda line: _event_line({"event": "warning", "line": line}))
        Runner(loaded, bound, options).run()
    except KeyboardInterrupt:
        code = 130
    except Exception:  # noqa: BLE001 - the parent computes the stages again and reports the error
        code = 1
    exit_now(code)  # the run waits for this process's end: no interpreter teardown (0.2-0.3 s)
