"""A batch job's share of the CPUs (runner.batch.job_cpus) and the runner options it computes
with on that share (runner.batch.job_options): those of `runner run` on a machine of that many
cores."""

from __future__ import annotations

from pathlib import Path

import pytest

from runner.batch import job_cpus, job_options
from runner.batch_manifest import Job


@pytest.mark.parametrize(
    ("jobs", "cpus", "at_once", "node_cpus", "expected"),
    [
        (1, 2, 2, 2, 2),  # one job on 2 cores (the default --workers): both
        (2, 2, 1, 2, 2),  # --workers 1: one job at a time, on both cores
        (4, 2, 2, 2, 1),  # four jobs, --workers 2: one core each
        (3, 16, 16, 16, 5),  # three shots on a 16-core node
        (4, 2, 4, 2, 1),  # more workers than cores: one each
        (3, 64, 3, 16, 16),  # a cluster of four 16-core nodes: at most one node's
        (100, 64, 100, 16, 1),
    ],
)
def test_job_cpus_is_the_jobs_share_at_most_a_node(jobs, cpus, at_once, node_cpus, expected):
    assert job_cpus(jobs=jobs, cpus=cpus, at_once=at_once, node_cpus=node_cpus) == expected


@pytest.mark.parametrize("cpus", [1, 2, 3, 7, 16])
def test_workers_jobs_at_once_still_fit(cpus):
    for workers in range(1, cpus + 1):
        for jobs in range(1, 2 * cpus + 1):
            at_once = min(jobs, workers)
            share = job_cpus(jobs=jobs, cpus=cpus, at_once=workers, node_cpus=cpus)
            assert at_once * share <= cpus  # the jobs of --workers run side by side
            assert at_once * (share + 1) > cpus  # and each takes as many as it could


@pytest.mark.parametrize("name", ["jobs", "cpus", "at_once", "node_cpus"])
@pytest.mark.parametrize("value", [0, -2, 1.0, True, "2"])
def test_job_cpus_arguments_must_be_positive_ints(name, value):
    arguments = {"jobs": 1, "cpus": 2, "at_once": 1, "node_cpus": 2, name: value}
    with pytest.raises(ValueError, match=f"{name} must be a positive int, got {value!r}"):
        job_cpus(**arguments)


@pytest.mark.parametrize(("cpus", "producers", "offload"), [(1, 2, False), (2, 2, True), (5, 5, True)])
def test_job_options_are_runner_runs_on_its_cpus(tmp_path: Path, cpus, producers, offload):
    job = Job(name="calm", pipeline="/p.yaml", clip="/c.mp4", overrides=("synthesize.mode=full",), out=str(tmp_path / "out"))
    events, warnings = [], []
    options = job_options(job, cpus=cpus, cache_dir=tmp_path / "cache", device="cpu", log=events.append, warn=warnings.append)
    assert (options.producers, options.offload, options.jobs) == (producers, offload, 1)
    assert options.overrides == ("synthesize.mode=full",)  # the offloaded child loads the pipeline with them
    assert options.out == tmp_path / "out" and options.cache.root == tmp_path / "cache" and options.device == "cpu"
    assert (options.until, options.force) in ((None, frozenset()), ((), frozenset()))
    options.log({"event": "x"})
    options.warn("w")
    assert events == [{"event": "x"}] and warnings == ["w"]
