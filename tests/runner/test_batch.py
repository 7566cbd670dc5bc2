"""`runner batch`: manifest validation (positioned errors), jobs on Ray with outputs
byte-identical to `runner run`, a failing job reported while the others finish, a worker that
dies retried, a batch killed at an observed event resumed; and the cache's locks holding across
processes (what every worker relies on).

One local Ray is started for the module (:func:`cluster`); the batches join it with
``--address`` (Ray's start-up is slow), except one that starts its own local Ray as a user's
``runner batch`` does. No Ray process of these tests is left running (checked).
"""

from __future__ import annotations

import json
import logging
import multiprocessing
import os
import re
import signal
import subprocess
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import ray  # in the test extra: a missing Ray fails these tests instead of skipping them

from runner.cache import CacheStore
from runner.stage import Context, Param, SequenceStage
from tests.runner.helpers import DATA, REPO, TINY, cli_env, read_log, run_cli, runner_cmd, tree_bytes

pytestmark = [pytest.mark.ray, pytest.mark.subprocess]


GRAPH = DATA / "graph.yaml"
SLEEP_S = "0.3"  # per chunk of test.add on the module's Ray workers: a kill lands inside the work


class CrashOnce(SequenceStage):
    """Mean intensity per frame, like ``test.mean``; the first time (no ``marker`` file yet) it
    creates the marker and kills its own process, as a worker lost to the OOM killer."""

    name = "batchtest.crash_once"
    version = "1"
    inputs = {"frames": "frames"}
    outputs = {"series": "series"}
    params = (Param("marker", str, "", "file marking the first try"),)

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        marker = Path(params["marker"])
        if not marker.exists():
            marker.write_text("crashed once")
            os._exit(3)
        means = [chunk.reshape(len(chunk), -1).mean(axis=1) for _, chunk in inputs["frames"].chunks()]
        return {"series": {"mean": np.concatenate(means)}}


TAG = "RUNNER_BATCH_TEST_TAG"  # in the environment of the Ray processes a test starts


def _tagged_pids(tag: str) -> set[int]:
    """Processes whose environment holds ``TAG=tag``: the Ray processes (daemons and workers
    inherit their starter's environment) of one test, whatever other sessions run."""
    pids = set()
    for proc in Path("/proc").iterdir():
        try:
            if proc.name.isdigit() and f"{TAG}={tag}".encode() in (proc / "environ").read_bytes().split(b"\0"):
                pids.add(int(proc.name))
        except OSError:
            continue
    return pids


def _assert_gone(tag: str, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while _tagged_pids(tag) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not _tagged_pids(tag), f"Ray processes left running: {sorted(_tagged_pids(tag))}"


@pytest.fixture(scope="module")
def site(plugin_site: Path, tmp_path_factory: pytest.TempPathFactory) -> str:
    """PYTHONPATH with the test stages and :class:`CrashOnce` registered."""
    folder = tmp_path_factory.mktemp("batch_site")
    info = folder / "runner_batch_test_plugins-0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: runner-batch-test-plugins\nVersion: 0\n")
    (info / "entry_points.txt").write_text(
        "[expression_mapping.stages]\nbatchtest.crash_once = tests.runner.test_batch:CrashOnce\n"
    )
    return os.pathsep.join([str(plugin_site), str(folder), str(REPO)])


@pytest.fixture(scope="module")
def cluster(site: str) -> str:
    """The address of a local Ray (2 CPUs) shared by the module's batches; its workers see the
    test stages and run test.add slowly."""
    tag = f"cluster-{os.getpid()}"
    knobs = {"PYTHONPATH": site, "RUNNER_TEST_SLEEP": SLEEP_S, TAG: tag}  # the workers' environment
    saved = {name: os.environ.get(name) for name in knobs}
    os.environ.update(knobs)
    try:
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name)
            else:
                os.environ[name] = value
    assert _tagged_pids(tag) - {os.getpid()}, "the Ray processes are not found by their tag"
    try:
        yield ray.get_runtime_context().gcs_address
    finally:
        ray.shutdown()
        _assert_gone(tag)


def _env(site: str, tmp_path: Path) -> dict[str, str]:
    """A driver's environment: the test stages, a fresh cache, and the token authentication of
    the module's Ray (``ray.init`` enables it for a local Ray; a driver joining one opts in)."""
    return {**cli_env(Path(site.split(os.pathsep)[0]), tmp_path / "cache"), "PYTHONPATH": site, "RAY_AUTH_MODE": "token"}


def _manifest(folder: Path, jobs: dict[str, dict[str, Any]], *, pipeline: Path = GRAPH) -> Path:
    path = folder / "shots.yaml"
    path.write_text(json.dumps({"defaults": {"pipeline": str(pipeline)}, "jobs": jobs}, indent=1))
    return path


TWO_JOBS = {"plus10": {"clip": str(TINY)}, "plus20": {"clip": str(TINY), "set": ["add.value=20"]}}


@pytest.fixture(scope="module")
def alone(site: str, tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[str, bytes]]:
    """Outputs of each of :data:`TWO_JOBS` run alone by `runner run` (a cache of its own)."""
    work = tmp_path_factory.mktemp("alone")
    outputs = {}
    for name, job in TWO_JOBS.items():
        sets = [a for text in job.get("set", []) for a in ("--set", text)]
        done = run_cli(
            "run", GRAPH, "--in", job["clip"], *sets, "--out", work / name / "out", env=_env(site, work / name), cwd=work
        )
        assert done.returncode == 0, done.stderr
        outputs[name] = tree_bytes(work / name / "out")
    assert outputs["plus10"] != outputs["plus20"]
    return outputs


def test_manifest_errors_are_positioned_and_nothing_runs(site, tmp_path):
    (tmp_path / "user" / "write").mkdir(parents=True)  # a user's folder where a stage publishes
    path = tmp_path / "shots.yaml"
    path.write_text(f"""defaults:
  pipeline: {GRAPH}
  colour: blue
jobs:
  ok: {{clip: {TINY}}}
  typo:
    clip: {TINY}
    set: [add.value=ten, nosuch.param=1]
  missing: {{clip: nowhere.mp4}}
  same_out: {{clip: {TINY}, out: out/ok}}
  user: {{clip: {TINY}, out: user}}
  wrong: {{clip: [1, 2], inputs: {{bogus: x}}}}
""")
    done = run_cli("batch", path, env=_env(site, tmp_path), cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    text = path.read_text().splitlines()

    def at(needle: str) -> str:  # file:line:column of the first line holding needle (1-based)
        row = next(i for i, line in enumerate(text) if needle in line)
        return f"error: {path}:{row + 1}:{text[row].index(needle) + 1}"

    lines = done.stderr.strip().splitlines()
    assert lines == [
        f"{at('colour')}: defaults.colour: unknown key (expected one of: pipeline, target, inputs, set)",
        f"{at('add.value=ten')}: jobs.typo.set: add.value: wrong type: expected int, got 'ten'",
        f"{at('nosuch')}: jobs.typo.set: nosuch.param: unknown stage 'nosuch' in this pipeline",
        f"{at('nowhere.mp4')}: jobs.missing.clip: {tmp_path / 'nowhere.mp4'}: no such file",
        f"{at('out/ok')}: jobs.same_out.out: same output folder as job 'ok': {tmp_path / 'out' / 'ok'}",
        f"{at('user}')}: jobs.user.out: {tmp_path / 'user' / 'write'}: exists without a manifest.json of runner; "
        "stage 'write' publishes there (move it away or choose another --out)",
        f"{at('[1, 2]')}: jobs.wrong.clip: wrong type: expected a path string, got [1, 2]",
        f"{at('{bogus')}: jobs.wrong.inputs: unknown pipeline input 'bogus' of {GRAPH} (declared: clip)",
    ]
    assert not (tmp_path / "out").exists() and not (tmp_path / "cache").exists()


@pytest.mark.parametrize(
    "text, expected",
    [
        ("jobs: &a {x: 1}\nother: *a\n", ["{manifest}:2:8: yaml: alias *a is not allowed (aliases are refused)"]),
        ("jobs: [\n", ["{manifest}:2:1: yaml: expected the node content, but found '<stream end>'"]),
        ("defaults: {}\n", ["{manifest}:1:1: jobs: missing: a manifest needs a `jobs` mapping with at least one job"]),
        # A pipeline with an error: said once, at its place in the pipeline, for the two jobs using it.
        (
            "jobs:\n  a: {pipeline: broken.yaml}\n  b: {pipeline: broken.yaml}\n",
            ["{broken}:3:13: stages.d.uses: unknown stage 'no.such' (see `runner stages`)"],
        ),
        # An input with no default and no value.
        (
            "jobs:\n  a: {pipeline: noclip.yaml}\n",
            ["{manifest}:2:3: jobs.a: inputs.clip: missing input: no value given (give it in the job or in `defaults`)"],
        ),
        # A pipeline without a video input: `clip` binds its folder input (a folder of photos).
        (
            "jobs:\n  a: {pipeline: photos.yaml, clip: nofolder}\n",
            ["{manifest}:2:36: jobs.a.clip: {tmp}/nofolder: no such folder"],
        ),
    ],
)
def test_manifest_file_problems(site, tmp_path, text, expected):
    (tmp_path / "broken.yaml").write_text("inputs: {clip: {type: video}}\nstages:\n  d: {uses: no.such}\n")
    (tmp_path / "noclip.yaml").write_text(
        "inputs: {clip: {type: video}}\nstages:\n  d: {uses: video.decode, inputs: {video: clip}}\n"
    )
    (tmp_path / "photos.yaml").write_text(
        "inputs: {photos: {type: dir}}\nstages:\n  d: {uses: pack.load, inputs: {pack: photos}}\n"
    )
    path = tmp_path / "shots.yaml"
    path.write_text(text)
    done = run_cli("batch", path, env=_env(site, tmp_path), cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr.splitlines() == [
        "error: " + line.format(manifest=path, broken=tmp_path / "broken.yaml", tmp=tmp_path) for line in expected
    ]


def test_batch_outputs_are_byte_identical_to_runner_run(site, cluster, alone, tmp_path):
    path = _manifest(tmp_path, TWO_JOBS)
    log = tmp_path / "log.jsonl"
    done = run_cli("batch", path, "--address", cluster, "--log-json", log, env=_env(site, tmp_path), cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    for name in TWO_JOBS:
        assert tree_bytes(tmp_path / "out" / name) == alone[name]
    events = read_log(log)
    assert [e["event"] for e in events][0] == "batch_start" and events[-1] == {**events[-1], "exit_code": 0, "done": 2}
    chunks = [e for e in events if e.get("event") == "chunk" and e["job"] == "plus20" and e["stage"] == "add"]
    # in any order: a job's producer threads (one per core) compute two chunks at once
    assert sorted((e["chunk"], e["chunks"]) for e in chunks) == [(k, 6) for k in range(1, 7)]
    lines = done.stdout.splitlines()
    for name in TWO_JOBS:
        # the first chunk resolved, which two producer threads may finish out of order
        assert f"[{name}] queued" in lines and any(
            re.fullmatch(rf"\[{name}\] running add chunk [12] of 6", line) for line in lines
        )
        assert any(line.startswith(f"[{name}] done in ") for line in lines)
    assert lines[-1].startswith("2 jobs: 2 done, 0 cached, 0 failed in ")
    # Run again: every job is cached.
    again = run_cli("batch", path, "--address", cluster, env=_env(site, tmp_path), cwd=tmp_path)
    assert again.returncode == 0 and again.stdout.splitlines()[-1].startswith("2 jobs: 0 done, 2 cached, 0 failed")


OFFLOADED = """inputs: {clip: {type: video}}
chunk_frames: 8
stages:
  decode: {uses: video.decode, inputs: {video: clip}}
  mean: {uses: test.mean, inputs: {frames: decode.frames}}
  table: {uses: test.table, inputs: {series: mean.series}}
  video: {uses: write.video, params: {crf: 20}, inputs: {frames: decode.frames}}
"""  # `mean` reads a source's frames while `video` computes: a tracker's place (runner.offload)


def test_a_lone_job_computes_as_runner_run_on_every_cpu(site, cluster, tmp_path):
    """One job on the module's 2-CPU Ray gets both CPUs and, as `runner run` on 2 cores, runs
    `mean` in a child process beside the run: the outputs are still `runner run`'s bytes."""
    pipeline = tmp_path / "offloaded.yaml"
    pipeline.write_text(OFFLOADED)
    alone = run_cli(
        "run",
        pipeline,
        "--in",
        TINY,
        "--out",
        tmp_path / "alone",
        "--log-json",
        tmp_path / "alone.jsonl",
        env=_env(site, tmp_path / "run"),
        cwd=tmp_path,
    )
    assert alone.returncode == 0, alone.stderr
    path = _manifest(tmp_path, {"lone": {"clip": str(TINY)}}, pipeline=pipeline)
    log = tmp_path / "log.jsonl"
    done = run_cli("batch", path, "--address", cluster, "--log-json", log, env=_env(site, tmp_path), cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert tree_bytes(tmp_path / "out" / "lone") == tree_bytes(tmp_path / "alone")
    events = read_log(log)
    assert events[0]["job_cpus"] == 2 and [e["cpus"] for e in events if e["event"] == "job_start"] == [2]
    for events in (read_log(tmp_path / "alone.jsonl"), events):  # both offload the same stage
        assert [e["stage"] for e in events if e["event"] == "offload"] == ["mean"]


def test_batch_killed_at_an_observed_event_resumes(site, cluster, alone, tmp_path):
    path = _manifest(tmp_path, TWO_JOBS)
    killed_log, resumed_log = tmp_path / "killed.jsonl", tmp_path / "resumed.jsonl"
    proc = subprocess.Popen(
        runner_cmd("batch", path, "--address", cluster, "--log-json", killed_log),
        env=_env(site, tmp_path),
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 90
        while not (
            killed_log.exists()
            and any(e.get("event") == "chunk" and e["stage"] == "add" and e["chunk"] == 2 for e in read_log(killed_log))
        ):
            assert proc.poll() is None and time.monotonic() < deadline, "the kill point was not reached"
            time.sleep(0.05)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert not any(e.get("event") == "batch_end" for e in read_log(killed_log))
    done = run_cli("batch", path, "--address", cluster, "--log-json", resumed_log, env=_env(site, tmp_path), cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    for name in TWO_JOBS:
        assert tree_bytes(tmp_path / "out" / name) == alone[name]

    # What the killed batch stored was not computed again.
    def ran(events: list[dict[str, Any]]) -> set[tuple[str, str, int]]:
        return {(e["job"], e["stage"], e["start"]) for e in events if e.get("event") == "chunk" and e["status"] == "ran"}

    before = ran(read_log(killed_log))
    assert before and not before & ran(read_log(resumed_log))


def test_batch_terminated_exits_130_with_its_batch_end_and_resumes(site, cluster, alone, tmp_path):
    """SIGTERM to `runner batch` is an interrupt, as for `runner run` and as SIGINT: exit 130,
    one line, a `batch_end` event; the next batch resumes to the same bytes."""
    path = _manifest(tmp_path, TWO_JOBS)
    log = tmp_path / "terminated.jsonl"
    proc = subprocess.Popen(
        runner_cmd("batch", path, "--address", cluster, "--log-json", log),
        env=_env(site, tmp_path),
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 90
        while not (log.exists() and any(e.get("event") == "chunk" and e["stage"] == "add" for e in read_log(log))):
            assert proc.poll() is None and time.monotonic() < deadline, "the signal point was not reached"
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=60)
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == 130 and stderr.strip() == "interrupted", stderr  # no native stack dump
    assert read_log(log)[-1] == {**read_log(log)[-1], "event": "batch_end", "status": "interrupted", "exit_code": 130}
    done = run_cli("batch", path, "--address", cluster, env=_env(site, tmp_path), cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    for name in TWO_JOBS:
        assert tree_bytes(tmp_path / "out" / name) == alone[name]


def test_dead_worker_is_retried_and_a_failing_job_is_reported(site, tmp_path):
    """On a local Ray started by the command (no --address), shut down at the end."""
    pipeline = tmp_path / "crash.yaml"
    pipeline.write_text(f"""inputs: {{clip: {{type: video}}}}
stages:
  decode: {{uses: video.decode, inputs: {{video: clip}}}}
  mean: {{uses: batchtest.crash_once, params: {{marker: {tmp_path / "marker"}}}, inputs: {{frames: decode.frames}}}}
  table: {{uses: test.table, inputs: {{series: mean.series}}}}
""")
    (tmp_path / "bad.mp4").write_bytes(b"not a video" * 100)
    path = _manifest(
        tmp_path, {"crashes_once": {"clip": str(TINY)}, "bad": {"clip": str(tmp_path / "bad.mp4")}}, pipeline=pipeline
    )
    log = tmp_path / "log.jsonl"
    tag = f"local-{tmp_path.name}-{os.getpid()}"
    done = run_cli("batch", path, "--workers", "1", "--log-json", log, env={**_env(site, tmp_path), TAG: tag}, cwd=tmp_path)
    assert done.returncode == 1, done.stderr
    _assert_gone(tag)
    # One job at a time (--workers 1), holding every CPU: in the workers' events, in time order,
    # another job's events begin only with its job_start.
    worker_events = sorted(
        (e for e in read_log(log) if e.get("job") and e["event"] not in ("job_queued", "job_end")), key=lambda e: e["time"]
    )
    for before, event in zip(worker_events, worker_events[1:]):
        assert event["job"] == before["job"] or event["event"] == "job_start", f"{before} then {event}"
    starts = [e for e in read_log(log) if e.get("event") == "job_start" and e["job"] == "crashes_once"]
    assert len(starts) == 2 and (tmp_path / "out" / "crashes_once" / "table" / "series.json").is_file()
    begin, end = (next(e for e in read_log(log) if e["event"] == kind) for kind in ("batch_start", "batch_end"))
    assert 0 < begin["ray_init_s"] < end["seconds"] and 0 < end["shutdown_s"] < end["seconds"] - begin["ray_init_s"]
    # The jobs' CPUs: the one job at a time gets the machine's (the sink a CPU of its own on one core)
    assert begin["cpus"] == begin["job_cpus"] == os.cpu_count()
    assert {e["cpus"] for e in read_log(log) if e["event"] == "job_start"} == {os.cpu_count()}
    rows = {line.split()[0]: line for line in done.stdout.splitlines()[-4:-1]}
    assert rows["crashes_once"].split()[1] == "done"
    assert rows["bad"].split()[1] == "failed" and f"stage 'decode' (video.decode): {tmp_path / 'bad.mp4'}" in rows["bad"]
    assert done.stdout.splitlines()[-1].startswith("2 jobs: 1 done, 0 cached, 1 failed")


def _count_under_lock(root: str, times: int) -> None:
    store = CacheStore(Path(root))
    counter = Path(root) / "counter"
    for _ in range(times):
        with store.locked("k" * 64):
            value = int(counter.read_text())
            time.sleep(0.001)
            counter.write_text(str(value + 1))
        with store.writing("e" * 64) as tmp:
            (tmp / "data.json").write_text(json.dumps(os.getpid()))
            store.commit("e" * 64, tmp, {"stage": "test"})


def test_cache_lock_and_commit_hold_across_processes(tmp_path):
    """Two processes on one cache: the entry lock excludes (no lost increment of a counter
    read-modified-written under it) and concurrent commits of one key leave one whole entry."""
    (tmp_path / "counter").write_text("0")
    context = multiprocessing.get_context("spawn")
    procs = [context.Process(target=_count_under_lock, args=(str(tmp_path), 40)) for _ in range(2)]
    for proc in procs:
        proc.start()
    for proc in procs:
        proc.join(60)
        assert proc.exitcode == 0
    assert (tmp_path / "counter").read_text() == "80"
    entries = list(CacheStore(tmp_path).iter_entries())
    assert len(entries) == 1 and json.loads((entries[0].path / "data.json").read_text()) == entries[0].record["pid"]
    assert not list((tmp_path / "locks").glob("*.lock")) and not list((tmp_path / "tmp").iterdir())
