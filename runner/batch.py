"""Many shots on Ray: the jobs of a batch manifest (:mod:`runner.batch_manifest`) run as Ray
tasks, each one exactly what ``runner run`` does for its command line.

Each job is one Ray task that runs the runner's in-process API
(:class:`runner.execute.Runner`, as ``runner run`` calls it) in a Ray worker process, against
the cache shared by all workers (a folder every host sees at the same path; its locks and
atomic renames hold across processes and hosts, see ``docs/batch.md``). Parallelism is per
job: the frame chunks of one job are computed one after another by its worker, as in
``runner run --jobs 1``, which is what makes the outputs byte-identical to ``runner run``'s.
A job's task asks for its share of the CPUs (:func:`job_cpus`: the CPUs over the jobs that run
at once, so that a batch of fewer jobs than CPUs still uses them all) and computes as
``runner run`` does on that many cores (:func:`job_options`: producer threads, and with two
CPUs or more the tracker in a child process; Ray sets ``OMP_NUM_THREADS`` to the task's CPUs).

Start-up: a local Ray is a chain of processes started one after another; the command starts
only those a batch on one machine uses (:func:`runner.batch_ray.start_local_ray`: the GCS, the
raylet and its two agents; no dashboard head, autoscaler monitor or log monitor; usage
statistics off, ``RAY_USAGE_STATS_ENABLED=0`` unless set), with a CPU for
the event sink actor where the jobs' CPUs are one per job (the raylet prestarts one worker
process per CPU: the sink and each of the first jobs then find a prestarted worker). ``--address`` joins a
running Ray with ``ray.init``. ``batch_start`` carries ``ray_init_s`` (the seconds until the
driver is connected) and ``batch_end`` ``shutdown_s`` (those of stopping or leaving the Ray);
``docs/batch.md`` gives the measured breakdown.

Failures: a stage that fails (:class:`runner.errors.StageFailed`, a bad input) fails its job
at once, with its one-line message; anything else (a worker process that died, an unexpected
exception) is retried by Ray up to ``retries`` times, resuming from the cache. A job that keeps
failing is reported and the other jobs finish. A batch killed at any moment resumes from the
cache when started again.

Progress: one line per job state change (queued, running, running STAGE chunk k of n,
retrying, done / cached / failed) and a final table; ``log`` receives every event of every job
(those of ``runner run --log-json`` with a ``job`` field, and ``job_*``/``batch_*`` events).
"""

from __future__ import annotations

import dataclasses
import os
import signal
import socket
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import ray
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

from runner.batch_manifest import Job
from runner.batch_ray import RAY_OPTIONS, start_local_ray
from runner.cache import CacheStore
from runner.config import ConfigError, bind_inputs, load_pipeline
from runner.errors import StageFailed
from runner.registry import Registry
from runner.signals import EXIT_OK, EXIT_STAGE

if TYPE_CHECKING:
    from runner.execute import Options

PROGRESS_EVERY_S = 2.0  # a job's chunk lines: a stage's first chunk, else at most one this often
WAIT_S = 0.25


def job_cpus(*, jobs: int, cpus: int, at_once: int, node_cpus: int) -> int:
    """The CPUs each job's Ray task asks for: its share of the CPUs among the jobs that run at
    once, at most one node's.

    Parameters
    ----------
    jobs
        The batch's jobs.
    cpus
        The CPUs the jobs share (a local Ray: this machine's; a cluster: all of its CPUs).
    at_once
        The most jobs that may run at once (``--workers``; on a cluster, ``jobs``).
    node_cpus
        The CPUs of the smallest node (a task's CPUs are all on one node).

    Returns
    -------
    int
        ``max(1, min(cpus // min(jobs, at_once), node_cpus))``: one job on 2 cores gets 2, three
        on a 16-core node 5 each, four on 2 cores (``--workers 2``) 1 each. ``at_once`` jobs of
        this many CPUs fit in ``cpus`` (where it is at least ``at_once``), so ``--workers N``
        still runs N jobs at once.

    Raises
    ------
    ValueError
        An argument is not a positive int.
    """
    for name, value in (("jobs", jobs), ("cpus", cpus), ("at_once", at_once), ("node_cpus", node_cpus)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    return max(1, min(cpus // min(jobs, at_once), node_cpus))


def job_options(
    job: Job, *, cpus: int, cache_dir: Path, device: str, log: Callable[[dict[str, Any]], None], warn: Callable[[str], None]
) -> Options:
    """The :class:`runner.execute.Options` of ``job`` on ``cpus`` CPUs: those ``runner run``
    uses on a machine of that many cores.

    Parameters
    ----------
    job
        A validated job (its ``out`` and ``overrides`` are used).
    cpus
        The CPUs its task holds (:func:`job_cpus`).
    cache_dir, device
        The shared cache folder and the resolved device (``cpu`` or ``cuda``).
    log, warn
        The runner's event and warning callbacks.

    Returns
    -------
    Options
        ``producers`` ``max(cpus, 2)`` (producer threads; at least two: one-CPU jobs side by
        side were slower with one each, ``docs/batch.md``), ``offload`` (a tracker in a child
        process) with two CPUs or more, ``overrides`` the job's ``--set`` (the child loads the
        pipeline with them); the rest ``runner run``'s defaults.
    """
    from runner.execute import Options  # the stages' imports: on the worker only

    return Options(
        cache=CacheStore(cache_dir),
        device=device,
        out=Path(job.out),
        producers=max(cpus, 2),
        offload=cpus >= 2,
        overrides=tuple(job.overrides),
        log=log,
        warn=warn,
    )


def run_job(job: Job, *, cpus: int, cache_dir: Path, device: str, emit: Callable[[dict[str, Any]], None]) -> dict[str, Any]:
    """Run one job in this process, as ``runner run`` runs its command line on ``cpus`` cores.

    Parameters
    ----------
    job
        A validated job.
    cpus
        The CPUs its task holds (:func:`job_cpus`; the options :func:`job_options`).
    cache_dir
        The shared cache folder.
    device
        ``cpu``, ``cuda`` or ``auto`` (resolved here, on the worker's host).
    emit
        Receives each event (the ``--log-json`` events of ``runner run``; ``chunk`` events
        also carry ``chunk`` (1-based) and ``chunks``, the stage's chunk count).

    Returns
    -------
    dict
        ``status`` (``done``, ``cached``: nothing ran, or ``failed``), ``seconds``, ``ran`` and
        ``cached`` (stage counts), ``error`` (one line) when failed. A failure that is not a
        stage's or the configuration's is raised (Ray retries the task).
    """
    from runner.execute import Runner, resolve_device  # the stages' imports: on the worker only

    started = time.perf_counter()
    emit({"event": "job_start", "host": socket.gethostname(), "pid": os.getpid(), "cpus": cpus})
    runner: Runner | None = None
    chunk_frames = 1

    def log(event: dict[str, Any]) -> None:
        if event.get("event") == "chunk" and runner is not None:
            count = len(runner.entries.get(event["stage"], ()))
            event = {**event, "chunk": event["start"] // chunk_frames + 1, "chunks": count}
        emit(event)

    try:
        loaded = load_pipeline(Path(job.pipeline), Registry.from_entry_points(), overrides=list(job.overrides))
        chunk_frames = loaded.chunk_frames
        bound = bind_inputs(loaded, clip=None if job.clip is None else Path(job.clip), named=list(job.named))
        options = job_options(
            job,
            cpus=cpus,
            cache_dir=cache_dir,
            device=resolve_device(device),
            log=log,
            warn=lambda line: emit({"event": "warning", "line": line}),
        )
        runner = Runner(loaded, bound, options)
        reports = runner.run()
    except (StageFailed, ConfigError) as exc:
        error = " / ".join(str(exc).splitlines())
        code = 2 if isinstance(exc, ConfigError) else 1
        emit({"event": "run_end", "status": "failed", "exit_code": code, "error": error})
        return {"status": "failed", "error": error, "seconds": time.perf_counter() - started, "ran": 0, "cached": 0}
    seconds = time.perf_counter() - started
    emit({"event": "run_end", "status": "ok", "exit_code": 0, "seconds": seconds})
    ran = sum(r.status in ("ran", "partial") for r in reports)
    return {
        "status": "done" if ran else "cached",
        "seconds": seconds,
        "ran": ran,
        "cached": sum(r.status == "cached" for r in reports),
    }


class EventSink:
    """A Ray actor collecting the workers' events for the driver (``add`` from the workers,
    ``take`` from the driver); one caller's calls arrive in order. It lives on the driver's
    node: a cluster node lost mid-batch does not take the batch's events with it."""

    def __init__(self) -> None:
        self._events: list[dict[str, Any]] = []

    def add(self, job: str, event: dict[str, Any]) -> None:
        self._events.append({"job": job, **event})

    def take(self) -> list[dict[str, Any]]:
        events, self._events = self._events, []
        return events


def _job_task(spec: dict[str, Any], cpus: int, cache_dir: str, device: str, sink: Any) -> dict[str, Any]:
    """The Ray task of one job: :func:`run_job` with its events sent to ``sink``. The first and
    the last event are awaited: the last so that every event is with the sink when the task's
    result is, the first so that a try whose worker dies right after starting is still seen
    (an actor call not yet sent is lost with its process). They are awaited through the
    reference's future, not ``ray.get``: a task blocked in ``ray.get`` or ``ray.wait`` lends its
    CPU to another task, which started a second job on a one-CPU Ray."""
    job = Job(**spec)

    def emit(event: dict[str, Any]) -> None:
        ref = sink.add.remote(job.name, {"time": time.time(), **event})
        if event.get("event") in ("job_start", "run_end"):
            ref.future().result()  # not ray.get/ray.wait: a task blocked in those lends its CPU to another task

    return run_job(job, cpus=cpus, cache_dir=Path(cache_dir), device=device, emit=emit)


@dataclasses.dataclass
class _State:
    """What the driver knows of one job."""

    job: Job
    status: str = "queued"
    attempts: int = 0
    stages: set[str] = dataclasses.field(default_factory=set)  # stages whose chunks were shown
    shown_at: float = 0.0
    result: dict[str, Any] = dataclasses.field(default_factory=dict)


def run_batch(
    jobs: list[Job],
    *,
    cache_dir: Path,
    device: str = "auto",
    workers: int | None = None,
    address: str | None = None,
    retries: int = 2,
    log: Callable[[dict[str, Any]], None] = lambda e: None,
    echo: Callable[[str], None] = print,
) -> int:
    """Run ``jobs`` on Ray; returns 0 if every job is done or cached, 1 if one failed.

    Parameters
    ----------
    jobs
        Validated jobs (:func:`runner.batch_manifest.load_manifest`).
    cache_dir
        The cache shared by every worker (made absolute here).
    device
        Passed to each job (``--device``).
    workers
        Jobs at once on a local Ray (default: this machine's CPUs); each job gets its share of
        the CPUs (:func:`job_cpus`); not with ``address``.
    address
        A Ray cluster to join (``ray.init(address=...)``) instead of starting a local Ray.
    retries
        Ray's ``max_retries`` of a job's task (a dead worker, an unexpected exception).
    log
        Receives every event (``--log-json``), each with ``time``.
    echo
        Receives the progress lines and the final table.

    Raises
    ------
    KeyboardInterrupt
        Interrupted: Ray is shut down (a local Ray's workers end; a cluster ends this driver's
        tasks) and the cache is left resumable. The SIGTERM handler in place when it is called
        (``runner``'s: an interrupt, as SIGINT) is put back after Ray's start-up replaced it.
    """
    if address is not None and workers is not None:
        raise ValueError(f"workers is for a local Ray only, got workers={workers} with address={address!r}")
    cache_dir = Path(cache_dir).resolve()
    started = time.perf_counter()
    on_sigterm = signal.getsignal(signal.SIGTERM)
    if address is None:
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # read by Ray and the processes it starts
        machine = os.cpu_count() or 1
        at_once = min(len(jobs), workers or machine)
        cpus = job_cpus(jobs=len(jobs), cpus=machine, at_once=at_once, node_cpus=machine)
        # The raylet prestarts a worker per CPU: where the jobs have one each, a CPU of the
        # sink's own gives it a worker besides theirs (and keeps the jobs at `at_once`).
        sink_cpus = 1 if cpus == 1 else 0
        stop_ray = start_local_ray(at_once * cpus + sink_cpus, note=echo)
    else:
        ray.init(address=address, **RAY_OPTIONS)
        stop_ray, sink_cpus = ray.shutdown, 0
        nodes = [int(node["Resources"].get("CPU", 0)) for node in ray.nodes() if node.get("Alive")]
        cpus = job_cpus(
            jobs=len(jobs),
            cpus=max(1, sum(nodes)),
            at_once=len(jobs),
            node_cpus=max(1, min((n for n in nodes if n > 0), default=1)),
        )
    if on_sigterm is not None and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, on_sigterm)  # ray.init replaced it (an exit with a native stack dump)
    ray_init_s = time.perf_counter() - started
    states: dict[str, _State] = {job.name: _State(job) for job in jobs}
    try:
        log(
            {
                "event": "batch_start",
                "time": time.time(),
                "jobs": len(jobs),
                "address": address,
                "cpus": ray.cluster_resources().get("CPU", 0) - sink_cpus,
                "job_cpus": cpus,
                "ray_init_s": ray_init_s,
            }
        )
        here = NodeAffinitySchedulingStrategy(node_id=ray.get_runtime_context().get_node_id(), soft=False)
        sink = ray.remote(num_cpus=sink_cpus, scheduling_strategy=here)(EventSink).remote()  # lost with the driver only
        if sink_cpus:  # created, holding its CPU, before a job can take that CPU; else its worker
            ray.get(sink.take.remote())  # starts beside the first jobs' (joining a Ray: none prestarted)
        task = ray.remote(num_cpus=cpus, max_retries=retries, retry_exceptions=True)(_job_task)
        pending = {}
        for job in jobs:
            pending[task.remote(dataclasses.asdict(job), cpus, str(cache_dir), device, sink)] = job.name
            _show(states[job.name], {"event": "job_queued"}, log, echo)
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1, timeout=WAIT_S)
            for event in ray.get(sink.take.remote()):
                _show(states[event["job"]], event, log, echo)
            for ref in done:
                state = states[pending.pop(ref)]
                try:
                    state.result = ray.get(ref)
                except ray.exceptions.RayError as exc:  # retries exhausted
                    cause = getattr(exc, "cause", None) or exc
                    state.result = {"status": "failed", "error": f"{type(cause).__name__}: {_first_line(cause)}"}
                _show(state, {"event": "job_end", **state.result}, log, echo)
    except KeyboardInterrupt:
        log({"event": "batch_end", "time": time.time(), "status": "interrupted", "exit_code": 130})
        raise
    finally:
        stopping = time.perf_counter()
        stop_ray()
    shutdown_s = time.perf_counter() - stopping
    seconds = time.perf_counter() - started
    counts = {s: sum(state.status == s for state in states.values()) for s in ("done", "cached", "failed")}
    code = EXIT_STAGE if counts["failed"] else EXIT_OK
    for line in _table(states.values()):
        echo(line)
    echo(f"{len(jobs)} jobs: {counts['done']} done, {counts['cached']} cached, {counts['failed']} failed in {seconds:.1f} s")
    log({"event": "batch_end", "time": time.time(), "exit_code": code, "seconds": seconds, "shutdown_s": shutdown_s, **counts})
    return code


def _show(state: _State, event: dict[str, Any], log: Callable[[dict[str, Any]], None], echo: Callable[[str], None]) -> None:
    """Log ``event`` of ``state``'s job and print a line if the job's state changed."""
    name, kind = state.job.name, event.get("event")
    log({"time": time.time(), "job": name, **event})
    line = None
    if kind == "job_queued":
        line = "queued"
    elif kind == "job_start":
        state.attempts += 1
        state.status = "running"
        line = f"running on {event['host']} (pid {event['pid']})" + (f", attempt {state.attempts}" if state.attempts > 1 else "")
    elif kind == "chunk" and event.get("chunks"):
        now = time.monotonic()
        if event["stage"] not in state.stages or now - state.shown_at >= PROGRESS_EVERY_S:
            state.stages.add(event["stage"])
            state.shown_at = now
            line = f"running {event['stage']} chunk {event['chunk']} of {event['chunks']}"
    elif kind == "warning":
        line = event["line"]
    elif kind == "job_end":
        state.status = event["status"]
        line = (
            f"failed: {event['error']}"
            if state.status == "failed"
            else f"{state.status} in {event['seconds']:.1f} s ({event['ran']} stages ran, {event['cached']} cached)"
        )
    if line is not None:
        echo(f"[{name}] {line}")


def _table(states: Iterable[_State]) -> list[str]:
    """The final table: one row per job."""
    rows = [("job", "status", "seconds", "ran/cached", "output or error")]
    for s in states:
        r = s.result
        what = r.get("error") if s.status == "failed" else s.job.out
        counts = f"{r['ran']}/{r['cached']}" if "ran" in r else "-"
        rows.append((s.job.name, s.status, f"{r['seconds']:.1f}" if "seconds" in r else "-", counts, what or ""))
    widths = [max(len(row[i]) for row in rows) for i in range(4)]
    return ["  ".join(cell.ljust(w) for cell, w in zip(row[:4], widths)) + "  " + row[4] for row in rows]


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else "no message"
