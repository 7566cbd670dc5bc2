"""Sequence stages that read a clip's frames, computed in a child process beside the run.

The stages before a run's streamed section are Python-heavy (tracking's per-point loop, importing
torch for the target's model): on threads of one process they take turns on the GIL and gain
nothing (docs/runner.md, "End-to-end speed"). So when a sequence stage that reads the frames of
a source (``video.decode``: a tracker, a landmarker) is ready while another stage is ready too,
the runner starts a child process that runs the pipeline up to that stage (``Runner`` with
``until``) against the same cache, inputs, parameters and device, and goes on with the other
stages meanwhile. The child commits the stage's entry as the run would (the cache's locks and
atomic commits hold across processes, as for ``runner batch``); once it has ended, the run
visits the stage and finds its entry. A child that fails leaves nothing: the run then computes
the stage itself, and reports its error as usual. The child's own events and warnings are not
the run's (as for a stage found in the cache: the run says the stage ran in a child process). A
child whose parent is gone (killed) stops within half a second; its cache is left resumable.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import runner

SPEC_VERSION = 1


def spec(*, pipeline: Path, overrides: list[str], bound: dict[str, Path], cache: Path, device: str,
         stage: str) -> str:
    """The child's command-line argument: what it needs to run ``pipeline`` up to ``stage`` as the
    parent would (JSON)."""
    return json.dumps({"version": SPEC_VERSION, "pipeline": str(pipeline), "overrides": list(overrides),
                       "bound": {name: str(path) for name, path in bound.items()}, "cache": str(cache),
                       "device": device, "until": stage})


def start(argument: str) -> subprocess.Popen:
    """Start the child process for :func:`spec`'s ``argument`` (its output is dropped)."""
    package_root = str(Path(runner.__file__).resolve().parent.parent)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [package_root, os.environ.get("PYTHONPATH")]))}
    return subprocess.Popen([sys.executable, "-c", "from runner.offload import main; main()", argument, str(os.getpid())],
                            env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _exit_when_orphaned(parent: int) -> None:
    """End this process once ``parent`` is no longer its parent (the run was killed)."""
    while os.getppid() == parent:
        time.sleep(0.5)
    os._exit(1)


def main(argv: list[str] | None = None) -> None:
    """The child: run the pipeline up to the spec's stage against the shared cache, publishing
    nothing; exit 0 once its entries are committed, 1 on any failure (the parent then computes
    the stage itself and reports why)."""
    from runner.cache import CacheStore
    from runner.config import load_pipeline
    from runner.execute import Options, Runner
    from runner.registry import Registry

    argument, parent = argv or sys.argv[1:]
    threading.Thread(target=_exit_when_orphaned, args=(int(parent),), daemon=True).start()
    args: dict[str, Any] = json.loads(argument)
    if args.get("version") != SPEC_VERSION:
        sys.exit(2)
    try:
        loaded = load_pipeline(Path(args["pipeline"]), Registry.from_entry_points(), overrides=args["overrides"])
        bound = {name: Path(path) for name, path in args["bound"].items()}
        options = Options(cache=CacheStore(Path(args["cache"])), device=args["device"], until=args["until"])
        Runner(loaded, bound, options).run()
    except KeyboardInterrupt:
        sys.exit(130)
    except Exception:  # noqa: BLE001 - the parent computes the stage again and reports the error
        sys.exit(1)
    sys.exit(0)
