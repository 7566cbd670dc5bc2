"""The streaming executor (producers, broadcast, stages on threads, a child process) against the
serial one, the reference: on every bundled pipeline both publish the same bytes and store the
same cache entries (keys and the digests of their outputs), and the plan of the finished cache is
every entry stored.

The eigenfeature training (``train.eigenfeatures``, a sequence stage: half a minute, computed by
the same code under both executors, on no stream) is computed by the serial run only; its
entry is copied into the streaming run's cache before that run, which finds it stored."""

from __future__ import annotations

import hashlib
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import av
import cv2
import pytest

from runner.cache import CacheStore
from runner.config import bind_inputs, load_pipeline
from runner.execute import Options, Runner
from runner.plan import make_plan
from runner.registry import Registry
from runner.serial import SerialExecutor
from tests.runner.helpers import DATA, ENTRY_POINTS, REPO, AddFrames

ASTRO = REPO / "fixtures" / "realface" / "astro.mp4"
PHOTOS = 4  # frames of astro.mp4 written as PNG photos


def _photos(folder: Path) -> Path:
    """A folder of the first ``PHOTOS`` frames of astro.mp4 as PNG files."""
    folder.mkdir()
    with av.open(str(ASTRO)) as container:
        for index, frame in enumerate(container.decode(video=0)):
            if index == PHOTOS:
                break
            cv2.imwrite(str(folder / f"photo_{index}.png"), frame.to_ndarray(format="bgr24"))
    return folder


# pipeline, its arguments (a callable of tmp_path for those it makes), whether above ~5 s a run
PIPELINES = [
    ("pipeline.yaml", lambda tmp: [], True),
    ("pipeline_3d.yaml", lambda tmp: [], True),
    ("pipeline_paper.yaml", lambda tmp: [], True),
    ("pipeline_eigen.yaml", lambda tmp: [], True),
    ("pipeline_eigen_real.yaml", lambda tmp: ["--input", f"performer_pack={REPO / 'fixtures' / 'packs' / 'performer'}"], True),
    ("pack_build.yaml", lambda tmp: ["--in", str(ASTRO)], False),
    ("pack_build_photos.yaml", lambda tmp: ["--in", str(_photos(tmp / "photos"))], False),
]


def _run(pipeline: str, args: list[str], executor: str, work: Path) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "runner.cli", "run", pipeline, *args, "--executor", executor]
        + ["--device", "cpu", "--out", str(work / "out"), "--cache-dir", str(work / "cache")],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr


def _published(out: Path) -> dict[str, str]:
    return {str(p.relative_to(out)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(out.rglob("*")) if p.is_file()}


def _seed_training(serial: Path, streaming: Path) -> None:
    """Copy the eigenfeature training's entries from the serial run's cache to the streaming one's."""
    for entry in CacheStore(serial).iter_entries():
        if entry.record.get("uses") == "train.eigenfeatures":
            shutil.copytree(entry.path, streaming / entry.path.relative_to(serial))


def _entries(cache: Path) -> dict[str, dict[str, str]]:
    """Per stored entry key, the digest of each output it recorded (none for a stream shape)."""
    return {
        entry.key: {port: output["digest"] for port, output in entry.record.get("outputs", {}).items()}
        for entry in CacheStore(cache).iter_entries()
    }


def test_serial_computes_on_the_calling_thread_and_stores_what_streaming_stores(tmp_path, monkeypatch):
    threads: dict[str, set[str]] = {"serial": set(), "streaming": set()}
    executor = ["serial"]
    process = AddFrames.process

    def recording(self, start, stop, inputs, params, ctx):
        threads[executor[0]].add(threading.current_thread().name)
        return process(self, start, stop, inputs, params, ctx)

    monkeypatch.setattr(AddFrames, "process", recording)
    pipeline = load_pipeline(DATA / "graph.yaml", Registry(entry_points=ENTRY_POINTS))
    bound = bind_inputs(pipeline, clip=None, named=[])
    for name, cls in (("serial", SerialExecutor), ("streaming", Runner)):
        executor[0] = name
        work = tmp_path / name
        reports = cls(pipeline, bound, Options(cache=CacheStore(work / "cache"), out=work / "out", producers=2, jobs=2)).run()
        assert {r.stage: r.status for r in reports}["add"] == "ran"
    assert threads["serial"] == {threading.current_thread().name}
    assert threads["streaming"] - threads["serial"]  # its producer threads: the two runs differ in how they compute
    assert _published(tmp_path / "streaming" / "out") == _published(tmp_path / "serial" / "out") != {}
    assert _entries(tmp_path / "streaming" / "cache") == _entries(tmp_path / "serial" / "cache")


@pytest.mark.subprocess
@pytest.mark.parametrize(
    ("pipeline", "arguments"),
    [pytest.param(name, args, marks=[pytest.mark.slow] if slow else [], id=name) for name, args, slow in PIPELINES],
)
def test_streaming_and_serial_publish_the_same_bytes_and_entries(pipeline, arguments, tmp_path):
    args = arguments(tmp_path)
    _run(pipeline, args, "serial", tmp_path / "serial")
    _seed_training(tmp_path / "serial" / "cache", tmp_path / "streaming" / "cache")
    _run(pipeline, args, "streaming", tmp_path / "streaming")
    serial, streaming = _published(tmp_path / "serial" / "out"), _published(tmp_path / "streaming" / "out")
    assert serial and streaming == serial
    assert _entries(tmp_path / "streaming" / "cache") == _entries(tmp_path / "serial" / "cache")
    loaded = load_pipeline(REPO / pipeline, Registry.from_entry_points())
    named = [a for flag, a in zip(args, args[1:]) if flag == "--input"]
    clip = next((Path(a) for flag, a in zip(args, args[1:]) if flag == "--in"), None)
    tasks = make_plan(
        loaded, bind_inputs(loaded, clip=clip, named=named), cache=CacheStore(tmp_path / "serial" / "cache"), device="cpu"
    )
    assert {task.status for task in tasks} <= {"cached", "on demand"}
