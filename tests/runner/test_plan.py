"""The planner: tasks, keys and reasons from the cache alone, checked against the entries a run
stores (the executor computes the keys itself, chunk by chunk)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from runner.cache import CacheStore
from runner.config import bind_inputs, load_pipeline
from runner.execute import Options, Runner
from runner.plan import Task, make_plan
from runner.registry import Registry
from tests.runner.helpers import DATA, ENTRY_POINTS, TINY, HalfSize

GRAPH = DATA / "graph.yaml"
CACHED_STAGES = {"add", "gray", "write", "mean", "table"}  # decode is uncached


def _plan(cache: Path, *overrides: str, force: frozenset[str] = frozenset(), until: tuple[str, ...] = ()) -> dict[str, Task]:
    pipeline = load_pipeline(GRAPH, Registry(entry_points=ENTRY_POINTS), overrides=list(overrides))
    tasks = make_plan(
        pipeline, bind_inputs(pipeline, clip=None, named=[]), cache=CacheStore(cache), device="cpu", force=force, until=until
    )
    return {task.stage: task for task in tasks}


def _run(cache: Path, out: Path, *overrides: str) -> None:
    pipeline = load_pipeline(GRAPH, Registry(entry_points=ENTRY_POINTS), overrides=list(overrides))
    Runner(pipeline, bind_inputs(pipeline, clip=None, named=[]), Options(cache=CacheStore(cache), out=out)).run()


def _stored(cache: Path) -> dict[str, set[str]]:
    """Per stage, the keys of its stored entries (not its stream shape's)."""
    keys: dict[str, set[str]] = {}
    for entry in CacheStore(cache).iter_entries():
        if "info" not in entry.record:
            keys.setdefault(entry.record["stage"], set()).add(entry.key)
    return keys


@pytest.fixture(scope="module")
def full(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A cache holding a complete run of the test graph."""
    root = tmp_path_factory.mktemp("full")
    _run(root / "cache", root / "out")
    return root / "cache"


def test_fresh_cache_plans_everything_and_writes_nothing(tmp_path):
    tasks = _plan(tmp_path / "cache")
    assert list(tasks) == ["decode", "add", "gray", "write", "mean", "table"]
    assert (tasks["decode"].status, len(tasks["decode"].keys), tasks["decode"].frames) == ("on demand", 6, 48)
    add = tasks["add"]
    assert (add.status, add.reason, add.chunks) == (
        "to compute",
        "never run with this configuration",
        tuple((s, s + 8) for s in range(0, 48, 8)),
    )
    assert add.stored == (False,) * 6 and "0/6 chunks cached" in add.report().line()
    assert (tasks["gray"].status, tasks["gray"].after, tasks["gray"].keys) == ("unknown", ("add",), ())
    assert tasks["gray"].report().status == "may run"
    assert tasks["mean"].status == "to compute" and tasks["table"].after == ("mean",)
    assert not (tmp_path / "cache").exists() or not list(CacheStore(tmp_path / "cache").iter_entries())


def test_full_cache_plans_the_keys_the_run_stored(full):
    before = sorted(e.key for e in CacheStore(full).iter_entries())
    tasks = _plan(full)
    assert {name: task.status for name, task in tasks.items()} == {
        "decode": "on demand",
        **dict.fromkeys(CACHED_STAGES, "cached"),
    }
    assert {name: set(tasks[name].keys) for name in CACHED_STAGES} == _stored(full)
    assert all(all(task.stored) for name, task in tasks.items() if name in CACHED_STAGES)
    assert sorted(e.key for e in CacheStore(full).iter_entries()) == before


def test_a_forced_stage_and_its_readers(full):
    tasks = _plan(full, force=frozenset({"add"}))
    assert (tasks["add"].status, tasks["add"].reason) == ("forced", "forced (--force)")
    assert set(tasks["add"].keys) == _stored(full)["add"]  # the keys it recomputes
    assert (tasks["gray"].status, tasks["gray"].after) == ("unknown", ("add",))
    assert tasks["write"].status == "unknown" and tasks["mean"].status == "cached"
    assert tasks["gray"].reason.startswith("after add (will run);")  # each stage waited for, with its status
    assert tasks["write"].reason.startswith("after gray (may run);")


def test_until_plans_only_those_stages_and_their_upstream(full):
    assert {name: task.status for name, task in _plan(full, until=("mean",)).items()} == {"decode": "on demand", "mean": "cached"}


def test_an_edited_parameter(full, tmp_path):
    tasks = _plan(full, "add.value=3")
    add = tasks["add"]
    assert add.status == "to compute" and "param value: 10 -> 3" in add.reason and not any(add.stored)
    assert not set(add.keys) & _stored(full)["add"]
    assert tasks["gray"].status == "unknown" and tasks["mean"].status == "cached"
    cache = tmp_path / "cache"
    shutil.copytree(full, cache)
    _run(cache, tmp_path / "out", "add.value=3")  # the run with the edit stores the planned keys
    assert set(add.keys) == _stored(cache)["add"] - _stored(full)["add"]


def test_a_stage_computing_its_own_shape_is_planned_from_the_shape_a_run_stored(tmp_path, monkeypatch):
    path = tmp_path / "resized.yaml"
    path.write_text(
        f"chunk_frames: 8\ninputs:\n  clip: {{type: video, default: {TINY}}}\nstages:\n"
        "  decode: {uses: video.decode, inputs: {video: clip}}\n"
        "  half: {uses: test.half_size, inputs: {frames: decode.frames}}\n"
        "  quarter: {uses: test.half_size_on_demand, inputs: {frames: half.frames}}\n"
        "  mean: {uses: test.mean, inputs: {frames: quarter.frames}}\n"
    )
    pipeline = load_pipeline(path, Registry(entry_points=ENTRY_POINTS))
    bound, cache = bind_inputs(pipeline, clip=None, named=[]), tmp_path / "cache"

    def plan() -> dict[str, Task]:
        return {task.stage: task for task in make_plan(pipeline, bound, cache=CacheStore(cache), device="cpu")}

    fresh = plan()  # the shape of `half` is not stored: to compute, with decode's 6 chunks
    assert (fresh["half"].status, fresh["half"].keys, fresh["half"].report().chunks) == ("to compute", (), 6)
    assert fresh["quarter"].after == ("half",) and fresh["mean"].after == ("quarter",)
    Runner(pipeline, bound, Options(cache=CacheStore(cache))).run()
    monkeypatch.setattr(HalfSize, "stream_info", lambda self, inputs, params: pytest.fail("the planner ran stream_info"))
    tasks = plan()
    assert {name: task.status for name, task in tasks.items()} == {
        "decode": "on demand",
        "half": "cached",
        "quarter": "on demand",
        "mean": "cached",
    }
    assert {name: set(tasks[name].keys) for name in ("half", "mean")} == _stored(cache)


def test_a_run_marks_the_stored_shape_used_so_gc_keeps_it_with_the_chunks(tmp_path):
    """`gc --older-than` removes entries not used for that long: a cached run uses the stream
    shape of a stage computing its own as it uses its chunks, so the planner still finds it."""
    path = tmp_path / "resized.yaml"
    path.write_text(
        f"chunk_frames: 8\ninputs:\n  clip: {{type: video, default: {TINY}}}\nstages:\n"
        "  decode: {uses: video.decode, inputs: {video: clip}}\n"
        "  half: {uses: test.half_size, inputs: {frames: decode.frames}}\n"
    )
    pipeline = load_pipeline(path, Registry(entry_points=ENTRY_POINTS))
    bound, store = bind_inputs(pipeline, clip=None, named=[]), CacheStore(tmp_path / "cache")
    Runner(pipeline, bound, Options(cache=store)).run()
    day = 24 * 3600
    for entry in store.iter_entries():
        os.utime(entry.path, (entry.path.stat().st_atime - 30 * day,) * 2)
    Runner(pipeline, bound, Options(cache=store)).run()  # all cached
    store.gc(older_than_s=day)
    assert [task.status for task in make_plan(pipeline, bound, cache=store, device="cpu")] == ["on demand", "cached"]
