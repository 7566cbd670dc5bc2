"""The ``runner`` command: run a pipeline, show its graph, list stages, manage the cache.

Exit codes: 0 ok, 1 a stage failed, 2 usage or configuration error, 130 interrupted.
"""

from __future__ import annotations

import contextlib
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from runner import signals
from runner.bundle import describe
from runner.cache import DEFAULT_DIR, ENV_VAR, CacheStore, default_cache_dir, holder_is_stale
from runner.config import ConfigError, Issue, Where, bind_inputs, load_pipeline
from runner.dag import to_dot, to_mermaid
from runner.errors import StageFailed
from runner.notes import bounded, one_line_warnings
from runner.registry import Registry, RegistryError
from runner.signals import EXIT_INTERRUPTED, EXIT_OK, EXIT_STAGE, EXIT_USAGE, INTERRUPTED, exit_now
from runner.stage import FrameStage

if TYPE_CHECKING:
    from runner.plan import Task

cache_dir_option = click.option(
    "--cache-dir",
    type=click.Path(file_okay=False, path_type=Path),
    envvar=ENV_VAR,
    default=None,
    help=f"Cache folder [env {ENV_VAR}; default {DEFAULT_DIR} under the current folder].",
)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="expression-mapping", message="%(prog)s %(version)s")
def cli() -> None:
    """Run a DAG of stages declared in a pipeline.yaml, caching every result so that an
    interrupted run resumes where it stopped."""


@cli.command()
@click.argument("pipeline", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--in", "clip", type=click.Path(path_type=Path), help="The clip bound to the pipeline's video input.")
@click.option("--input", "named", multiple=True, metavar="NAME=PATH", help="Bind any pipeline input (repeatable).")
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    default=Path("out"),
    show_default=True,
    help="Where `files` outputs are published, one folder per stage.",
)
@click.option(
    "--dry-run",
    is_flag=True,
    help="Print the plan: per stage, cached / will run / may run / on demand, and why; compute nothing.",
)
@click.option("--force", multiple=True, metavar="STAGE", help="Recompute STAGE even if cached (repeatable).")
@click.option("--until", metavar="STAGE", multiple=True, help="Run only STAGE and the stages it depends on (repeatable).")
@click.option(
    "--set",
    "overrides",
    multiple=True,
    metavar="STAGE.PARAM=VALUE",
    help="Override a parameter, typed by its schema (repeatable).",
)
@click.option(
    "--device",
    type=click.Choice(["cpu", "cuda", "auto"]),
    default="auto",
    show_default=True,
    help="Where torch stages compute; auto = CUDA when available.",
)
@click.option(
    "--jobs", type=click.IntRange(min=1), default=1, show_default=True, help="Chunks of a frame stage computed at once (threads)."
)
@click.option(
    "--executor",
    type=click.Choice(["streaming", "serial"]),
    default="streaming",
    show_default=True,
    help="streaming: stages read streams as they are computed, on threads (and a child process); "
    "serial: one stage at a time, chunks in order, the reference (same outputs and cache entries).",
)
@click.option(
    "--log-json",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Write one JSON event per line (stages, chunks, outcome) to this file.",
)
@cache_dir_option
def run(
    pipeline: Path,
    clip: Path | None,
    named: tuple[str, ...],
    out: Path,
    dry_run: bool,
    force: tuple[str, ...],
    until: tuple[str, ...],
    overrides: tuple[str, ...],
    device: str,
    jobs: int,
    executor: str,
    log_json: Path | None,
    cache_dir: Path | None,
) -> int:
    """Run PIPELINE (a pipeline.yaml)."""
    from runner.execute import Options, Runner, resolve_device  # here: `dag`, `stages` start faster without it
    from runner.plan import make_plan
    from runner.serial import SerialExecutor

    loaded = load_pipeline(pipeline, Registry.from_entry_points(), overrides=list(overrides))
    unknown = [
        Issue(Where(flag), name, "unknown stage in this pipeline")
        for flag, names in (("--force", force), ("--until", until))
        for name in names
        if name not in loaded.stages
    ]
    if unknown:
        raise ConfigError(unknown)
    bound = bind_inputs(loaded, clip=clip, named=list(named))
    resolved = resolve_device(device)
    if resolved == "cuda" and device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise click.UsageError("--device cuda: CUDA is not available on this machine")
    INTERRUPTED.clear()
    log_file = open(log_json, "w", encoding="utf-8") if log_json else None

    def log(event: dict[str, Any]) -> None:
        if log_file is not None:
            log_file.write(json.dumps({"time": time.time(), **event}) + "\n")
            log_file.flush()
        if INTERRUPTED.is_set() and event.get("event") != "run_end":
            raise KeyboardInterrupt  # the signal's own exception was lost (see runner.signals.interrupt)

    store = CacheStore(cache_dir or default_cache_dir())
    if dry_run:
        from runner.publish import refused

        why = refused(out)
        if why:  # the plan of a run that would be refused
            raise ConfigError([Issue(Where("--out"), str(out), why)])
        try:
            _print_plan(
                pipeline, make_plan(loaded, bound, cache=store, device=resolved, force=frozenset(force), until=until), log
            )
        finally:
            if log_file is not None:
                log_file.close()
        return EXIT_OK
    options = Options(
        cache=store,
        device=resolved,
        jobs=jobs,
        force=frozenset(force),
        until=until,
        out=out,
        offload=True,
        overrides=tuple(overrides),
        progress=sys.stderr.isatty(),
        log=log,
        echo=click.echo,
        warn=lambda line: click.echo(line, err=True),
    )
    started = time.perf_counter()
    try:
        (SerialExecutor if executor == "serial" else Runner)(loaded, bound, options).run()
        seconds = time.perf_counter() - started
        log({"event": "run_end", "status": "ok", "exit_code": EXIT_OK, "seconds": seconds})
    except StageFailed as exc:
        media = [
            str(bound[ref.port])
            for name in loaded.ancestors(exc.node.name)
            for ref in loaded.stages[name].inputs.values()
            if ref.stage is None and loaded.inputs[ref.port].type == "video" and ref.port in bound
        ]
        if media:  # name the clip whose content failed the stage
            exc.args = (f"{exc} [{', '.join(dict.fromkeys(media))}]",)
        log({"event": "run_end", "status": "failed", "exit_code": EXIT_STAGE, "error": str(exc)})
        raise
    except KeyboardInterrupt:
        log({"event": "run_end", "status": "interrupted", "exit_code": EXIT_INTERRUPTED})
        raise
    finally:
        if log_file is not None:
            log_file.close()
    click.echo(f"done in {seconds:.2f} s; outputs in {out}/")
    return EXIT_OK


def _print_plan(pipeline: Path, tasks: list[Task], log: Callable[[dict[str, Any]], None]) -> None:
    """``--dry-run``: one line per task (cached / will run / may run / on demand, and why), each
    also logged as a ``stage`` event."""
    click.echo(f"dry run of {pipeline}: nothing is run")
    for task in tasks:
        report = task.report()
        log({"event": "stage", **asdict(report)})
        click.echo(report.line())
    log({"event": "run_end", "status": "ok", "exit_code": EXIT_OK, "seconds": 0.0})


@cli.command()
@click.argument("manifest", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--workers", type=click.IntRange(min=1), help="Jobs at once on the local Ray [default: the CPUs].")
@click.option("--address", help="Join this Ray cluster (`auto`, HOST:PORT) instead of starting a local Ray.")
@click.option(
    "--retries",
    type=click.IntRange(min=0),
    default=2,
    show_default=True,
    help="Retries of a job whose worker died or raised (a failed stage is not retried).",
)
@click.option(
    "--device",
    type=click.Choice(["cpu", "cuda", "auto"]),
    default="auto",
    show_default=True,
    help="Where torch stages compute, resolved on each worker.",
)
@click.option(
    "--log-json",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Write one JSON event per line (every job's `runner run` events, with `job`) to this file.",
)
@cache_dir_option
def batch(
    manifest: Path,
    workers: int | None,
    address: str | None,
    retries: int,
    device: str,
    log_json: Path | None,
    cache_dir: Path | None,
) -> int:
    """Run the jobs of MANIFEST (shots.yaml, see docs/batch.md) on Ray, each as `runner run` would."""
    from runner.batch_manifest import load_manifest

    if workers is not None and address is not None:
        raise click.UsageError("--workers is for the local Ray; a cluster's CPUs are its own (drop one)")
    jobs = load_manifest(manifest, Registry.from_entry_points())
    try:
        from runner.batch import run_batch
    except ImportError as exc:
        raise click.UsageError(f"runner batch needs Ray ({exc}): pip install 'expression-mapping[batch]'") from None
    with open(log_json, "w", encoding="utf-8") if log_json else contextlib.nullcontext() as log_file:

        def log(event: dict[str, Any]) -> None:
            if log_file is not None:
                log_file.write(json.dumps(event) + "\n")
                log_file.flush()

        return run_batch(
            jobs,
            cache_dir=cache_dir or default_cache_dir(),
            device=device,
            workers=workers,
            address=address,
            retries=retries,
            log=log,
            echo=click.echo,
        )


@cli.command()
@click.argument("pipeline", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--mermaid", "fmt", flag_value="mermaid", default=True, help="Mermaid flowchart (default).")
@click.option("--dot", "fmt", flag_value="dot", help="Graphviz dot.")
def dag(pipeline: Path, fmt: str) -> int:
    """Print the stage graph of PIPELINE."""
    loaded = load_pipeline(pipeline, Registry.from_entry_points())
    click.echo(to_dot(loaded) if fmt == "dot" else to_mermaid(loaded), nl=False)
    return EXIT_OK


@cli.command()
def stages() -> int:
    """List the registered stages with their ports and parameters."""
    registry = Registry.from_entry_points()
    for name in registry.names():
        cls = registry.get(name)
        shape = "frame" if issubclass(cls, FrameStage) else "sequence"
        click.echo(f"{name}  (v{cls.version}, {shape} stage)  {cls.doc}")
        for port, kind in cls.inputs.items():
            optional = ", optional" if port in cls.optional_inputs else ""
            click.echo(f"    in   {port}: {describe(kind)}{optional}")
        for port, kind in cls.outputs.items():
            click.echo(f"    out  {port}: {kind}")
        for p in cls.params:
            allowed = f" one of {', '.join(map(repr, p.choices))};" if p.choices else ""
            allowed += f" matching {p.pattern};" if p.pattern else ""
            if p.min is not None or p.max is not None:
                allowed += f" {'' if p.min is None else f'{p.min} <= '}{p.name}{'' if p.max is None else f' <= {p.max}'};"
            click.echo(f"    param {p.name}: {p.type_name} = {p.default!r} —{allowed} {p.help}")
    return EXIT_OK


@cli.group()
def cache() -> None:
    """Inspect and clean the cache."""


@cache.command("ls")
@cache_dir_option
def cache_ls(cache_dir: Path | None) -> int:
    """List complete entries (newest use last) and current locks."""
    store = CacheStore(cache_dir or default_cache_dir())
    total = 0
    rows = sorted(store.iter_entries(), key=lambda e: e.path.stat().st_mtime)
    for entry in rows:
        size = sum(p.stat().st_size for p in entry.path.rglob("*") if p.is_file())
        total += size
        record = entry.record
        what = "chunk {}-{}".format(*record["range"]) if "range" in record else ("stream info" if "info" in record else "whole")
        age = time.time() - entry.path.stat().st_mtime
        click.echo(
            f"{entry.key[:16]}  {record.get('stage', '?'):<14} {record.get('uses', '?'):<18} "
            f"{what:<14} {size / 1e6:9.2f} MB  used {age / 3600:7.1f} h ago"
        )
    for path, holder in store.locks():
        state = "stale" if holder and holder_is_stale(holder) else "held"
        click.echo(f"lock {path.name[:16]}  pid {holder.get('pid') if holder else '?'}  {state}")
    click.echo(f"{len(rows)} entries, {total / 1e6:.2f} MB in {store.root}")
    return EXIT_OK


def _days(ctx: click.Context, param: click.Parameter, value: float | None) -> float | None:
    """``--older-than``: a finite number of days, 0 or more (click's range lets NaN through)."""
    if value is not None and not math.isfinite(value):
        raise click.BadParameter(f"expected a finite number of days, got {value}", ctx, param)
    return value


@cache.command("gc")
@click.option(
    "--older-than",
    type=click.FloatRange(min=0),
    callback=_days,
    metavar="DAYS",
    help="Also remove entries not used for DAYS days.",
)
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    default=Path("out"),
    show_default=True,
    help="An output folder whose leftovers of killed publishes (.STAGE.PID.tmp/.old) are removed.",
)
@cache_dir_option
def cache_gc(older_than: float | None, out: Path, cache_dir: Path | None) -> int:
    """Remove leftovers of dead runs (temporary folders, stale locks, half-published output
    folders) and, with --older-than, entries not used recently."""
    from runner.publish import remove_leftovers

    store = CacheStore(cache_dir or default_cache_dir())
    counts = store.gc(older_than_s=None if older_than is None else older_than * 86400)
    published = remove_leftovers(out)
    click.echo(
        f"removed {counts['entries']} entries, {counts['tmp']} temporary folders, {counts['locks']} stale locks "
        f"({counts['bytes'] / 1e6:.2f} MB), {published} leftover output folders in {out}"
    )
    return EXIT_OK


@cache.command("clear")
@cache_dir_option
def cache_clear(cache_dir: Path | None) -> int:
    """Remove every cache entry."""
    store = CacheStore(cache_dir or default_cache_dir())
    counts = store.clear()
    click.echo(f"removed {counts['entries']} entries ({counts['bytes'] / 1e6:.2f} MB) from {store.root}")
    return EXIT_OK


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point: maps errors to exit codes, one line each, no traceback.

    Python warnings of the libraries are one line each (:func:`runner.notes.one_line_warnings`).
    SIGINT and SIGTERM both interrupt the run (exit 130, the cache left resumable;
    :func:`runner.signals.install`).

    Called without ``argv`` (the process is the command: the console script, ``python -m``), it
    ends the process with :func:`exit_now` instead of the interpreter's teardown; with ``argv``
    (called from Python) it raises ``SystemExit`` as usual."""
    signals.install()
    one_line_warnings()
    try:
        code = cli.main(args=argv, prog_name="runner", standalone_mode=False)
    except click.ClickException as exc:
        exc.show()
        code = exc.exit_code
    except ConfigError as exc:
        for issue in exc.issues:
            click.echo(f"error: {bounded(str(issue))}", err=True)
        code = EXIT_USAGE
    except RegistryError as exc:
        click.echo(f"error: {bounded(str(exc))}", err=True)
        code = EXIT_USAGE
    except StageFailed as exc:
        click.echo(f"error: {bounded(str(exc))}", err=True)
        code = EXIT_STAGE
    except (KeyboardInterrupt, click.Abort) as exc:
        if isinstance(exc.__cause__, EOFError) and not INTERRUPTED.is_set():
            raise exc.__cause__  # click turns an EOFError into Abort: a fault of ours, not an interrupt
        click.echo("interrupted", err=True)
        code = EXIT_INTERRUPTED
    except OSError as exc:  # an unusable --cache-dir, --out or --log-json path
        where = f"{exc.filename}: " if exc.filename else ""
        click.echo(f"error: {bounded(f'{where}{exc.strerror or exc}')}", err=True)
        code = EXIT_USAGE
    if argv is None:
        exit_now(code or 0)
    sys.exit(code or 0)


if __name__ == "__main__":
    main()
