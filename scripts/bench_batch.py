"""Batch benchmarks: `python scripts/bench.py batch [--json] [--work DIR] [--clips DIR]`.

Four fixture jobs (``fixtures/clips/calm.mp4`` and ``live.mp4``, 48 frames 320x240 each, each
through ``pipeline.yaml`` and through ``pipeline_paper.yaml`` onto the bundled target; distinct
output folders), every side with a fresh cache, every command a new process as a user runs it
(start-up included):

- ``batch_speedup_2workers``: the 4 jobs run one after another by ``runner run`` (one fresh
  cache), over the same 4 jobs in one ``runner batch --workers 2`` (a local Ray started by the
  command, one fresh cache), in the same bench run; target >= 1.6 on a 2-core machine.
- ``batch_overhead_ratio``: one job (calm through pipeline.yaml) through ``runner batch
  --workers 1`` over the same job through ``runner run``; target <= 1.15. The difference is
  Ray's start-up and shut-down (a local Ray: its daemons and a worker process) and the driver.
- ``batch_seq_s``, ``batch_2workers_s``, ``batch_one_job_s``, ``run_one_job_s``: the wall times
  behind the ratios.
- The one-job batch's start-up, from its ``--log-json`` events: ``batch_driver_s`` (launch to
  ``ray.init``: Python, the command's imports, the manifest's check, ``import ray``),
  ``batch_ray_init_s`` (starting the local Ray, ``runner/batch_ray.py``, and connecting the
  driver), ``batch_job_start_s`` (launch to the job starting on a Ray worker) and
  ``batch_shutdown_s`` (disconnecting and stopping the local Ray).
- ``batch_attached_overhead_ratio``: the one job through ``runner batch --address`` joining a
  local Ray that the bench started beforehand (as a studio keeps one running with ``ray start
  --head``), over ``run_one_job_s``: the batch without Ray's start-up and shut-down;
  ``batch_attached_one_job_s`` its wall time.
- ``batch_outputs_identical``: 1 if every file the 4-job batch published is byte-identical to
  what ``runner run`` published for the same job.

The one-job timings are the best of ``ONE_JOB_REPEATS`` interleaved runs (each start-up part
its own best) (the first also warms
the page cache with the stages' libraries); the 4-job timings are one run each (a side takes
minutes). The machine may be shared: every row carries ``load``, ``/proc/loadavg``'s three
averages when the bench started and when it ended.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
ONE_JOB_REPEATS = 2


def _jobs(clips: Path) -> dict[str, dict]:
    """The four jobs as manifest entries (absolute paths)."""
    jobs = {}
    for clip in ("calm", "live"):
        jobs[f"{clip}_landmarks"] = {"pipeline": str(REPO / "pipeline.yaml"), "clip": str(clips / f"{clip}.mp4")}
        jobs[f"{clip}_paper"] = {"pipeline": str(REPO / "pipeline_paper.yaml"), "clip": str(clips / f"{clip}.mp4"),
                                 "inputs": {"init": str(clips / f"{clip}_track0.csv")}}
    return jobs


def _run_args(job: dict, out: Path) -> list[str]:
    """``runner run`` arguments of a manifest entry."""
    named = [a for name, path in job.get("inputs", {}).items() for a in ("--input", f"{name}={path}")]
    return ["run", job["pipeline"], "--in", job["clip"], *named, "--out", str(out)]


def _tree(folder: Path) -> dict[str, bytes]:
    """Relative path -> bytes of every file under ``folder``."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _timed(*commands: list[str], cache: Path, env: dict[str, str] | None = None) -> float:
    """Wall seconds of ``runner`` commands run one after another in new processes (environment
    ``env``, default this one's), on a fresh ``cache``; a command that fails stops the bench."""
    shutil.rmtree(cache, ignore_errors=True)
    started = time.perf_counter()
    for args in commands:
        done = subprocess.run([sys.executable, "-m", "runner.cli", *args, "--cache-dir", str(cache)],
                              cwd=REPO, capture_output=True, text=True, env=env)
        if done.returncode != 0:
            raise RuntimeError(f"runner {' '.join(args)} failed ({done.returncode}): {done.stderr.strip()[-2000:]}")
    return time.perf_counter() - started


def _batch(jobs: dict[str, dict], folder: Path, workers: int | None = None, address: str | None = None) -> list[str]:
    """``runner batch`` arguments for ``jobs`` on a local Ray of ``workers`` or on the Ray at
    ``address``, their manifest written under ``folder``."""
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    manifest = folder / "shots.yaml"
    manifest.write_text(json.dumps({"jobs": {name: {**job, "out": str(folder / "out" / name)}
                                             for name, job in jobs.items()}}, indent=1))
    where = ["--address", address] if address else ["--workers", str(workers)]
    return ["batch", str(manifest), *where, "--log-json", str(folder / "log.jsonl")]


def _start_up(log: Path, launched: float) -> dict[str, float]:
    """The start-up parts of a one-job batch launched at ``launched`` (epoch s), from its events."""
    events = {e["event"]: e for e in map(json.loads, log.read_text().splitlines()) if "job" not in e or
              e["event"] == "job_start"}
    begun = events["batch_start"]["time"] - events["batch_start"]["ray_init_s"]
    return {"driver_s": begun - launched, "ray_init_s": events["batch_start"]["ray_init_s"],
            "job_start_s": events["job_start"]["time"] - launched, "shutdown_s": events["batch_end"]["shutdown_s"]}


def _attached(jobs: dict[str, dict], work: Path) -> float:
    """Best wall seconds of ``ONE_JOB_REPEATS`` ``runner batch --address`` of ``jobs`` joining a
    local Ray started here first (its workers import this tree's packages), then shut down."""
    import ray

    saved = os.environ.get("PYTHONPATH")
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), saved]))  # for the Ray processes
    try:
        ray.init(num_cpus=os.cpu_count(), include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
    finally:
        if saved is None:
            del os.environ["PYTHONPATH"]
        else:
            os.environ["PYTHONPATH"] = saved
    try:
        args = _batch(jobs, work / "batch_attached", address=ray.get_runtime_context().gcs_address)
        env = {**os.environ, "RAY_AUTH_MODE": "token"}  # the token of a local ray.init
        return min(_timed(args, cache=work / "cache_attached", env=env) for _ in range(ONE_JOB_REPEATS))
    finally:
        ray.shutdown()


def run(args) -> list[dict]:
    clips = Path(args.extra[args.extra.index("--clips") + 1]) if "--clips" in args.extra else REPO / "fixtures" / "clips"
    work = Path(args.work).resolve() / "batch"
    work.mkdir(parents=True, exist_ok=True)
    jobs = _jobs(clips.resolve())
    first = dict(list(jobs.items())[:1])
    load_before = Path("/proc/loadavg").read_text().split()[:3]

    run_one, batch_one, parts = [], [], []
    for _ in range(ONE_JOB_REPEATS):  # interleaved: the load of other sessions moves both alike
        run_one.append(_timed(_run_args(first[next(iter(first))], work / "run_out" / "one"),
                              cache=work / "cache_run_one"))
        launched = time.time()
        batch_one.append(_timed(_batch(first, work / "batch_one", 1), cache=work / "cache_batch_one"))
        parts.append(_start_up(work / "batch_one" / "log.jsonl", launched))
    run_one, batch_one = min(run_one), min(batch_one)
    start_up = {name: min(p[name] for p in parts) for name in parts[0]}
    attached = _attached(first, work)
    seq = _timed(*[_run_args(job, work / "run_out" / name) for name, job in jobs.items()], cache=work / "cache_seq")
    two = _timed(_batch(jobs, work / "batch_two", 2), cache=work / "cache_batch_two")

    identical = all(_tree(work / "run_out" / name) == _tree(work / "batch_two" / "out" / name) for name in jobs)
    load = f"{' '.join(load_before)} -> {' '.join(Path('/proc/loadavg').read_text().split()[:3])}"
    rows = [("batch_speedup_2workers", seq / two, "x"), ("batch_overhead_ratio", batch_one / run_one, "x"),
            ("batch_attached_overhead_ratio", attached / run_one, "x"), ("batch_attached_one_job_s", attached, "s"),
            ("batch_seq_s", seq, "s"), ("batch_2workers_s", two, "s"), ("batch_one_job_s", batch_one, "s"),
            ("run_one_job_s", run_one, "s"), *[(f"batch_{name}", value, "s") for name, value in start_up.items()],
            ("batch_outputs_identical", int(identical), "bool")]
    return [{"bench": "batch", "metric": m, "value": v, "unit": u, "load": load, "cpus": os.cpu_count()}
            for m, v, u in rows]
