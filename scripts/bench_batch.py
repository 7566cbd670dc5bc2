"""Batch benchmarks: `python scripts/bench.py batch [--json] [--work DIR] [--clips DIR] [--e2e]`.

Four fixture jobs (``fixtures/clips/calm.mp4`` and ``live.mp4``, 48 frames 320x240 each, each
through ``pipeline.yaml`` and through ``pipeline_paper.yaml`` onto the bundled target; distinct
output folders), every side with a fresh cache, every command a new process as a user runs it
(start-up included):

- ``batch_speedup_2workers``: the 4 jobs run one after another by ``runner run`` (one fresh
  cache), over the same 4 jobs in one ``runner batch --workers 2`` (a local Ray started by the
  command, one fresh cache), in the same bench run; target >= 1.6 on a 2-core machine.
- ``batch_overhead_ratio``: one job (calm through pipeline.yaml) through ``runner batch
  --workers 1`` (the job on every CPU, as ``runner run``) over the same job through ``runner
  run``; target <= 1.15. The difference is Ray's start-up and shut-down (a local Ray: its
  daemons and worker processes) and the driver.
- ``batch_seq_s``, ``batch_2workers_s``, ``batch_one_job_s``, ``run_one_job_s``: the wall times
  behind the ratios.
- The one-job batch's start-up, from its ``--log-json`` events: ``batch_driver_s`` (launch to
  ``ray.init``: Python, the command's imports, the manifest's check, ``import ray``),
  ``batch_ray_init_s`` (starting the local Ray, ``runner/batch_ray.py``, and connecting the
  driver), ``batch_job_start_s`` (launch to the job starting on a Ray worker) and
  ``batch_shutdown_s`` (disconnecting and stopping the local Ray).
- ``batch_attached_overhead_ratio``: the one job through ``runner batch --address`` joining a
  local Ray that the bench started beforehand (as a studio keeps one running with ``ray start
  --head``; its workers at nice 0, as ``docs/batch.md`` advises for such a Ray, not Ray's 15,
  which under other load would measure the priority rather than the batch), over
  ``run_one_job_s``: the batch without Ray's start-up and shut-down; ``batch_attached_one_job_s``
  its wall time.
- ``batch_outputs_identical``: 1 if every file the 4-job batch (one CPU per job) and the
  one-job batch (both CPUs, the tracker in a child process) published is byte-identical to what
  ``runner run`` published for the same job; ``batch_outputs_pixels_identical`` 1 if they are
  byte-identical except EXR frames whose decoded pixels are identical (and ``exr/manifest.json``
  but for those frames' sizes and hashes): the EXR writer's deflated bytes are known to vary
  between runs (``docs/batch.md``, *Two findings*), which is the writer's, not the batch's.
- With ``--e2e``: the e2e demo job (``pipeline_paper.yaml`` on the 300-frame 640x480 demo clip
  ``live`` onto the 600x800 target, ``synthesize.mode=full``, every output written: the job of
  ``bench.py e2e``, its fixture set generated under ``--work`` on first use) through ``runner
  batch`` (the default ``--workers``) over the same job through ``runner run``:
  ``batch_e2e_overhead_ratio``, with ``batch_e2e_one_job_s`` and ``run_e2e_one_job_s``, the best
  of ``ONE_JOB_REPEATS`` interleaved runs: the fixed cost of a batch against a real shot; and
  ``batch_e2e_attached_overhead_ratio`` (with ``batch_e2e_attached_one_job_s``), the same job
  through ``runner batch --address`` joining a Ray started beforehand, over ``run_e2e_one_job_s``.

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
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
ONE_JOB_REPEATS = 2


def _jobs(clips: Path) -> dict[str, dict]:
    """The four jobs as manifest entries (absolute paths)."""
    jobs = {}
    for clip in ("calm", "live"):
        jobs[f"{clip}_landmarks"] = {"pipeline": str(REPO / "pipeline.yaml"), "clip": str(clips / f"{clip}.mp4")}
        jobs[f"{clip}_paper"] = {
            "pipeline": str(REPO / "pipeline_paper.yaml"),
            "clip": str(clips / f"{clip}.mp4"),
            "inputs": {"init": str(clips / f"{clip}_track0.csv")},
        }
    return jobs


def _e2e_job(work: Path) -> dict[str, dict]:
    """The e2e demo job as a manifest entry (absolute paths), its fixture set under ``work``."""
    from scripts.bench_geometry import fixture_set

    root = fixture_set(None, work, demo=True)
    return {
        "demo": {
            "pipeline": str(REPO / "pipeline_paper.yaml"),
            "clip": str(root / "clips" / "live.mp4"),
            "inputs": {
                "init": str(root / "clips" / "live_track0.csv"),
                "performer": str(root / "packs" / "performer"),
                "target": str(root / "packs" / "target"),
            },
            "set": ["synthesize.mode=full"],
        }
    }


def _run_args(job: dict, out: Path) -> list[str]:
    """``runner run`` arguments of a manifest entry."""
    named = [a for name, path in job.get("inputs", {}).items() for a in ("--input", f"{name}={path}")]
    sets = [a for text in job.get("set", []) for a in ("--set", text)]
    return ["run", job["pipeline"], "--in", job["clip"], *named, *sets, "--out", str(out)]


def _tree(folder: Path) -> dict[str, bytes]:
    """Relative path -> bytes of every file under ``folder``."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _pixels_of(path: str, data: bytes) -> bytes | dict:
    """What must match of one published file: an EXR frame's pixels (native channel types), an
    EXR manifest without its frames' sizes and hashes, else the bytes."""
    if path.endswith(".exr"):
        import OpenImageIO as oiio

        with tempfile.NamedTemporaryFile(suffix=".exr") as file:
            file.write(data)
            file.flush()
            image = oiio.ImageInput.open(file.name)
            pixels = image.read_image(image.spec().format).tobytes()
            image.close()
        return pixels
    if path.endswith("manifest.json"):
        manifest = json.loads(data)
        for entry in manifest.get("files", []):
            if entry.get("path", "").endswith(".exr"):
                entry.pop("size", None), entry.pop("sha256", None)
        return manifest
    return data


def _same_pixels(a: dict[str, bytes], b: dict[str, bytes]) -> bool:
    """Whether two :func:`_tree` results hold the same files with the same :func:`_pixels_of`."""
    return a.keys() == b.keys() and all(a[k] == b[k] or _pixels_of(k, a[k]) == _pixels_of(k, b[k]) for k in a)


def _timed(*commands: list[str], cache: Path, env: dict[str, str] | None = None) -> float:
    """Wall seconds of ``runner`` commands run one after another in new processes (environment
    ``env``, default this one's), on a fresh ``cache``; a command that fails stops the bench."""
    shutil.rmtree(cache, ignore_errors=True)
    started = time.perf_counter()
    for args in commands:
        done = subprocess.run(
            [sys.executable, "-m", "runner.cli", *args, "--cache-dir", str(cache)],
            cwd=REPO,
            capture_output=True,
            text=True,
            env=env,
        )
        if done.returncode != 0:
            raise RuntimeError(f"runner {' '.join(args)} failed ({done.returncode}): {done.stderr.strip()[-2000:]}")
    return time.perf_counter() - started


def _batch(jobs: dict[str, dict], folder: Path, workers: int | None = None, address: str | None = None) -> list[str]:
    """``runner batch`` arguments for ``jobs`` on a local Ray of ``workers`` (default: the
    command's) or on the Ray at ``address``, their manifest written under ``folder``."""
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    manifest = folder / "shots.yaml"
    manifest.write_text(
        json.dumps({"jobs": {name: {**job, "out": str(folder / "out" / name)} for name, job in jobs.items()}}, indent=1)
    )
    where = ["--address", address] if address else ["--workers", str(workers)] if workers else []
    return ["batch", str(manifest), *where, "--log-json", str(folder / "log.jsonl")]


def _start_up(log: Path, launched: float) -> dict[str, float]:
    """The start-up parts of a one-job batch launched at ``launched`` (epoch s), from its events."""
    events = {e["event"]: e for e in map(json.loads, log.read_text().splitlines()) if "job" not in e or e["event"] == "job_start"}
    begun = events["batch_start"]["time"] - events["batch_start"]["ray_init_s"]
    return {
        "driver_s": begun - launched,
        "ray_init_s": events["batch_start"]["ray_init_s"],
        "job_start_s": events["job_start"]["time"] - launched,
        "shutdown_s": events["batch_end"]["shutdown_s"],
    }


def _attached(jobs: dict[str, dict], work: Path, name: str) -> float:
    """Best wall seconds of ``ONE_JOB_REPEATS`` ``runner batch --address`` of ``jobs`` joining a
    local Ray started here first (its workers import this tree's packages), then shut down; its
    folders under ``work`` named by ``name``."""
    import ray

    saved = os.environ.get("PYTHONPATH")
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), saved]))  # for the Ray processes
    try:
        ray.init(
            num_cpus=os.cpu_count(),
            include_dashboard=False,
            log_to_driver=False,
            logging_level=logging.ERROR,
            _system_config={"worker_niceness": 0},
        )
    finally:
        if saved is None:
            del os.environ["PYTHONPATH"]
        else:
            os.environ["PYTHONPATH"] = saved
    try:
        args = _batch(jobs, work / f"batch_attached_{name}", address=ray.get_runtime_context().gcs_address)
        env = {**os.environ, "RAY_AUTH_MODE": "token"}  # the token of a local ray.init
        return min(_timed(args, cache=work / f"cache_attached_{name}", env=env) for _ in range(ONE_JOB_REPEATS))
    finally:
        ray.shutdown()


def _one_job(job: dict[str, dict], work: Path, name: str, workers: int | None) -> tuple[float, float, list[dict]]:
    """Best wall seconds of ``job`` through ``runner run`` and through ``runner batch`` (of
    ``workers``), ``ONE_JOB_REPEATS`` interleaved runs each (the load of other sessions moves both
    alike), and each batch's start-up parts; the outputs are left in ``work/run_out/NAME`` and
    ``work/batch_NAME/out/JOB``."""
    run_s, batch_s, parts = [], [], []
    for _ in range(ONE_JOB_REPEATS):
        run_s.append(_timed(_run_args(job[next(iter(job))], work / "run_out" / name), cache=work / f"cache_run_{name}"))
        launched = time.time()
        batch_s.append(_timed(_batch(job, work / f"batch_{name}", workers), cache=work / f"cache_batch_{name}"))
        parts.append(_start_up(work / f"batch_{name}" / "log.jsonl", launched))
    return min(run_s), min(batch_s), parts


def run(args) -> list[dict]:
    clips = Path(args.extra[args.extra.index("--clips") + 1]) if "--clips" in args.extra else REPO / "fixtures" / "clips"
    work = Path(args.work).resolve() / "batch"
    work.mkdir(parents=True, exist_ok=True)
    jobs = _jobs(clips.resolve())
    first = dict(list(jobs.items())[:1])
    load_before = Path("/proc/loadavg").read_text().split()[:3]

    run_one, batch_one, parts = _one_job(first, work, "one", 1)
    start_up = {name: min(p[name] for p in parts) for name in parts[0]}
    attached = _attached(first, work, "one")
    seq = _timed(*[_run_args(job, work / "run_out" / name) for name, job in jobs.items()], cache=work / "cache_seq")
    two = _timed(_batch(jobs, work / "batch_two", 2), cache=work / "cache_batch_two")

    pairs = [(_tree(work / "run_out" / name), _tree(work / "batch_two" / "out" / name)) for name in jobs]
    pairs.append((_tree(work / "run_out" / "one"), _tree(work / "batch_one" / "out" / next(iter(first)))))
    identical, same_pixels = all(a == b for a, b in pairs), all(_same_pixels(a, b) for a, b in pairs)
    e2e = []
    if "--e2e" in args.extra:
        e2e_job = _e2e_job(Path(args.work).resolve())
        run_e2e, batch_e2e, _ = _one_job(e2e_job, work, "e2e", None)
        attached_e2e = _attached(e2e_job, work, "e2e")
        e2e = [
            ("batch_e2e_overhead_ratio", batch_e2e / run_e2e, "x"),
            ("batch_e2e_one_job_s", batch_e2e, "s"),
            ("run_e2e_one_job_s", run_e2e, "s"),
            ("batch_e2e_attached_overhead_ratio", attached_e2e / run_e2e, "x"),
            ("batch_e2e_attached_one_job_s", attached_e2e, "s"),
        ]
    load = f"{' '.join(load_before)} -> {' '.join(Path('/proc/loadavg').read_text().split()[:3])}"
    rows = [
        ("batch_speedup_2workers", seq / two, "x"),
        ("batch_overhead_ratio", batch_one / run_one, "x"),
        ("batch_attached_overhead_ratio", attached / run_one, "x"),
        ("batch_attached_one_job_s", attached, "s"),
        ("batch_seq_s", seq, "s"),
        ("batch_2workers_s", two, "s"),
        ("batch_one_job_s", batch_one, "s"),
        ("run_one_job_s", run_one, "s"),
        *[(f"batch_{name}", value, "s") for name, value in start_up.items()],
        ("batch_outputs_identical", int(identical), "bool"),
        ("batch_outputs_pixels_identical", int(same_pixels), "bool"),
        *e2e,
    ]
    return [{"bench": "batch", "metric": m, "value": v, "unit": u, "load": load, "cpus": os.cpu_count()} for m, v, u in rows]
