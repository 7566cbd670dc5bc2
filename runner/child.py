"""The child process that :func:`runner.offload.start` starts: a new interpreter that runs a
pipeline up to some stages against the run's cache (:mod:`runner.offload`).

Apart from :mod:`runner.offload` because it builds a :class:`runner.execute.Runner`, which
imports :mod:`runner.offload`.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from runner.cache import CacheStore
from runner.config import load_pipeline
from runner.execute import Options, Runner
from runner.offload import SPEC_VERSION, run_child
from runner.registry import Registry


def main(argv: list[str] | None = None) -> None:
    """The child started by :func:`runner.offload.start`: run the pipeline up to the spec's stages against the
    shared cache, publishing nothing, its events on standard output
    (:func:`runner.offload.run_child`)."""
    argument, parent = argv or sys.argv[1:]
    args: dict[str, Any] = json.loads(argument)
    if args.get("version") != SPEC_VERSION:
        sys.exit(2)

    def make_runner(**events: Any) -> Runner:
        loaded = load_pipeline(Path(args["pipeline"]), Registry.from_entry_points(), overrides=args["overrides"])
        bound = {name: Path(path) for name, path in args["bound"].items()}
        return Runner(
            loaded,
            bound,
            Options(cache=CacheStore(Path(args["cache"])), device=args["device"], until=tuple(args["until"]), **events),
        )

    run_child(make_runner, parent=int(parent))
