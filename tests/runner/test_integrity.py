"""The cache's guarantees, in-process: damaged entries are detected when read or published and
recomputed (never used, never a traceback); what a result depends on is in its key (input file
suffix, files recorded with runner.depends); publishing replaces only what an earlier publish
wrote; a full disk names the stage and the file."""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from runner import depends, digest, outputs, publish
from runner.cache import CacheStore
from runner.cli import cli
from runner.config import ConfigError, bind_inputs, load_pipeline
from runner.execute import Options, Runner, StageFailed
from runner.registry import Registry
from runner.stage import FrameStage, Param, SequenceStage, StreamInfo

N, H, W = 12, 3, 4


def truth() -> np.ndarray:
    """Frame t filled with 10 t + 1 (no frame is all zeros, like a black streak would be)."""
    return np.broadcast_to((10 * np.arange(N, dtype=np.uint8) + 1)[:, None, None, None], (N, H, W, 1)).copy()


class Ramp(FrameStage):
    name, version = "i.ramp", "1"
    outputs = {"frames": "frames"}

    def stream_info(self, inputs, params):
        return StreamInfo(N, 25.0, W, H)

    def process(self, start, stop, inputs, params, ctx):
        return {"frames": truth()[start:stop]}


class Sums(SequenceStage):
    """Per-frame sums of a stream; ``note`` changes the key only (to make it read again)."""

    name, version = "i.sums", "1"
    inputs = {"frames": "frames"}
    outputs = {"sums": "sums"}
    params = (Param("note", str, "", "ignored"),)

    def run(self, inputs, params, ctx):
        sums = np.concatenate([c.reshape(len(c), -1).sum(axis=1) for _, c in inputs["frames"].chunks()])
        return {"sums": {"sum": sums}}


class Table(SequenceStage):
    """Writes the sums as ``sums.json`` (a ``files`` output)."""

    name, version = "i.table", "1"
    inputs = {"sums": "sums"}
    outputs = {"table": "files"}
    params = (Param("note", str, "", "ignored"), Param("enabled", bool, True, "False: writes no file"))

    def run(self, inputs, params, ctx):
        folder = ctx.files_dir("table")
        if params["enabled"]:
            (folder / "sums.json").write_text(json.dumps(inputs["sums"]["sum"].tolist()))
        return {"table": None}


class Parse(SequenceStage):
    """Parses its ``init`` file by suffix (``.csv`` numbers; anything else: its length), and
    reads the file named by ``extra`` (recorded with runner.depends, as a layout loader does)."""

    name, version = "i.parse", "1"
    inputs = {"init": "file"}
    outputs = {"value": "value"}
    params = (Param("extra", str, "", "a file read besides the inputs"),)

    def run(self, inputs, params, ctx):
        text = Path(inputs["init"]).read_text()
        value = float(sum(map(float, text.split(",")))) if inputs["init"].suffix == ".csv" else float(len(text))
        if params["extra"]:
            depends.depends_on(params["extra"])
            value += float(Path(params["extra"]).read_text())
        return {"value": {"v": np.array([value])}}


class Drifting(Ramp):
    """Ramp whose frames change each time they are computed (a stage that is not deterministic)."""

    name = "i.drifting"
    computed = 0

    def process(self, start, stop, inputs, params, ctx):
        Drifting.computed += 1
        return {"frames": truth()[start:stop] + Drifting.computed}


REGISTRY = Registry(classes=[Ramp, Sums, Table, Parse, Drifting])
CHAIN = """
chunk_frames: 4
stages:
  ramp: {uses: i.ramp}
  sums: {uses: i.sums, inputs: {frames: ramp.frames}}
  table: {uses: i.table, inputs: {sums: sums.sums}}
"""
PARSE = """
inputs:
  init: {type: file}
stages:
  parse: {uses: i.parse, inputs: {init: init}}
"""


class Recorder:
    def __init__(self):
        self.warnings: list[str] = []
        self.events: list[dict] = []


def run(
    tmp_path: Path, text: str = CHAIN, *, overrides=(), named=(), out: Path | None = None, recorder: Recorder | None = None
) -> Runner:
    path = tmp_path / "p.yaml"
    path.write_text(textwrap.dedent(text))
    pipeline = load_pipeline(path, REGISTRY, overrides=list(overrides))
    recorder = recorder or Recorder()
    options = Options(
        cache=CacheStore(tmp_path / "cache"),
        out=out if out is not None else tmp_path / "out",
        warn=recorder.warnings.append,
        log=recorder.events.append,
    )
    runner = Runner(pipeline, bind_inputs(pipeline, clip=None, named=list(named)), options)
    runner.run()
    return runner


def statuses(recorder: Recorder) -> dict[str, str]:
    return {e["stage"]: e["status"] for e in recorder.events if e.get("event") == "stage"}


def entry_files(tmp_path: Path, stage: str, name: str) -> list[Path]:
    return sorted(
        p for e in CacheStore(tmp_path / "cache").iter_entries() if e.record.get("stage") == stage for p in e.path.rglob(name)
    )


def published_sums(tmp_path: Path) -> list[int]:
    return json.loads((tmp_path / "out" / "table" / "sums.json").read_text())


EXPECTED = truth().reshape(N, -1).sum(axis=1).tolist()


# -- damaged entries ------------------------------------------------------------------------


def test_frame_chunks_store_their_digest_and_are_computed_again_when_read_later(tmp_path):
    """Frames are not stored: ramp's entries record the digest of each chunk's frames only, and
    a reader whose key changed gets the frames computed again, equal to the first ones."""
    run(tmp_path)
    entries = [
        e for e in CacheStore(tmp_path / "cache").iter_entries() if e.record.get("stage") == "ramp" and "range" in e.record
    ]
    assert len(entries) == 3 and entry_files(tmp_path, "ramp", "*.npy") == []
    for entry in entries:
        start, stop = entry.record["range"]
        assert entry.record["outputs"]["frames"] == {"type": "frames", "digest": digest.array_digest(truth()[start:stop])}
    recorder = Recorder()
    run(tmp_path, overrides=["sums.note=again"], recorder=recorder)  # sums reads every chunk
    assert published_sums(tmp_path) == EXPECTED and recorder.warnings == []
    assert [(e["start"], e["stop"]) for e in recorder.events if e.get("event") == "recompute"] == [(0, 4), (4, 8), (8, 12)]
    assert statuses(recorder)["ramp"] == "cached"


def test_frames_computed_again_that_differ_from_their_digest_are_reported(tmp_path):
    """A stage that does not compute the same frames twice: its frames computed again for a
    later reader differ from the digests its entries recorded; each chunk is a
    ``nondeterministic`` event, the stage one warning line."""
    chain = CHAIN.replace("i.ramp", "i.drifting")
    run(tmp_path, chain)
    recorder = Recorder()
    run(tmp_path, chain, overrides=["sums.note=again"], recorder=recorder)
    assert [(e["stage"], e["start"], e["stop"], e["ports"]) for e in recorder.events if e.get("event") == "nondeterministic"] == [
        ("ramp", s, s + 4, ["frames"]) for s in (0, 4, 8)
    ]
    assert len(recorder.warnings) == 1 and "'ramp'" in recorder.warnings[0] and "not deterministic" in recorder.warnings[0]


def test_damaged_bundle_of_a_sequence_stage_is_recomputed(tmp_path):
    run(tmp_path)
    bundle = entry_files(tmp_path, "sums", "sums.npz")[0]
    bundle.write_bytes(bundle.read_bytes()[:-7])
    recorder = Recorder()
    run(tmp_path, overrides=["table.note=again"], recorder=recorder)
    assert published_sums(tmp_path) == EXPECTED
    assert len(recorder.warnings) == 1 and "'sums'" in recorder.warnings[0]


def test_damaged_completion_record_is_a_miss_and_replaced(tmp_path):
    run(tmp_path)
    record = entry_files(tmp_path, "sums", "complete.json")[0]
    record.write_text("{not json")
    recorder = Recorder()
    run(tmp_path, recorder=recorder)
    assert statuses(recorder)["sums"] == "ran"
    assert json.loads(record.read_text())["stage"] == "sums"


def test_damaged_cached_file_is_not_published(tmp_path):
    run(tmp_path)
    cached = entry_files(tmp_path, "table", "sums.json")[0]
    cached.write_text("[0, 0]")
    (tmp_path / "out" / "table" / "sums.json").unlink()  # publishing copies from the cache again
    recorder = Recorder()
    run(tmp_path, recorder=recorder)
    assert published_sums(tmp_path) == EXPECTED
    manifest = json.loads((tmp_path / "out" / "table" / "manifest.json").read_text())
    assert manifest["files"][0]["sha256"] == hashlib.sha256((tmp_path / "out" / "table" / "sums.json").read_bytes()).hexdigest()
    assert len(recorder.warnings) == 1 and "'table'" in recorder.warnings[0]


def test_published_files_share_no_bytes_with_the_cache(tmp_path):
    """A published file is a file of its own: damaging the cache entry leaves the published
    output intact (and the entry is caught and recomputed when next read), and rewriting the
    published file in place leaves the entry intact."""
    run(tmp_path)
    cached = entry_files(tmp_path, "table", "sums.json")[0]
    published = tmp_path / "out" / "table" / "sums.json"
    assert published.stat().st_ino != cached.stat().st_ino
    original = cached.read_bytes()
    with open(cached, "r+b") as f:  # a byte flipped in the entry
        f.write(b"{")
    assert published.read_bytes() == original
    cached.write_bytes(original)
    published.write_text("[0]")  # a tool rewriting the output in place
    assert cached.read_bytes() == original


def test_published_file_damaged_in_place_is_published_again(tmp_path):
    """A byte of a published file flipped in place (same size, new mtime): a rerun into the same
    --out, all cached, publishes it again from the (intact) entry."""
    run(tmp_path)
    published = tmp_path / "out" / "table" / "sums.json"
    time.sleep(0.05)  # past the filesystem's timestamp granularity: the write gets a new mtime
    with open(published, "r+b") as f:
        f.write(b"{")
    recorder = Recorder()
    run(tmp_path, recorder=recorder)
    assert set(statuses(recorder).values()) == {"cached"}
    assert published_sums(tmp_path) == EXPECTED and recorder.warnings == []


def test_stage_publishing_no_file_publishes_an_empty_folder(tmp_path):
    run(tmp_path, overrides=["table.enabled=false"])
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["table"]
    assert [p.name for p in (tmp_path / "out" / "table").iterdir()] == ["manifest.json"]
    assert json.loads((tmp_path / "out" / "table" / "manifest.json").read_text())["files"] == []


def flip_keeping_times(path: Path) -> None:
    """Flip one byte in the middle of ``path``, then set its access and modification times back
    (bit rot, or a tool that restores times): its size, mtime and inode are unchanged."""
    before = path.stat()
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    with open(path, "r+b") as f:
        f.write(data)
    os.utime(path, ns=(before.st_atime_ns, before.st_mtime_ns))


def test_cache_file_damaged_with_its_times_restored_is_recomputed_not_published(tmp_path):
    """Publishing hashes every byte it copies: a cache file damaged in place with its size,
    mtime and inode kept is caught when published into a new --out, its entry recomputed, and
    the published bytes are the ones the manifest names."""
    run(tmp_path)
    cached = entry_files(tmp_path, "table", "sums.json")[0]
    flip_keeping_times(cached)
    recorder = Recorder()
    run(tmp_path, out=tmp_path / "out2", recorder=recorder)
    published = tmp_path / "out2" / "table" / "sums.json"
    assert published.read_bytes() == (tmp_path / "out" / "table" / "sums.json").read_bytes()
    manifest = json.loads((tmp_path / "out2" / "table" / "manifest.json").read_text())
    assert manifest["files"][0]["sha256"] == hashlib.sha256(published.read_bytes()).hexdigest()
    assert len(recorder.warnings) == 1 and "'table'" in recorder.warnings[0] and "damaged" in recorder.warnings[0]
    assert [e["stage"] for e in recorder.events if e["event"] == "damaged"] == ["table"]
    table = [e for e in recorder.events if e["event"] == "stage" and e["stage"] == "table"]
    assert [(e["status"], e["reason"]) for e in table] == [
        ("cached", ""),
        ("ran", "computed again to publish: 1 damaged cache entry"),
    ]


def test_published_file_damaged_with_its_times_restored_is_published_again(tmp_path):
    """A published file damaged in place with its size, mtime and inode kept has another ctime
    (setting the times back sets it): a rerun into the same --out publishes it again."""
    run(tmp_path)
    published = tmp_path / "out" / "table" / "sums.json"
    time.sleep(0.05)  # past the filesystem's timestamp granularity: the ctime moves
    flip_keeping_times(published)
    run(tmp_path)
    assert published_sums(tmp_path) == EXPECTED


# -- what is in a key -----------------------------------------------------------------------


def test_input_file_suffix_is_in_the_key(tmp_path):
    (tmp_path / "init.csv").write_text("1,2,3")
    (tmp_path / "init.txt").write_text("1,2,3")
    first = run(tmp_path, PARSE, named=["init=" + str(tmp_path / "init.csv")])
    second = run(tmp_path, PARSE, named=["init=" + str(tmp_path / "init.txt")])
    assert first.values[("parse", "value")].get()["v"][0] == 6.0
    assert second.values[("parse", "value")].get()["v"][0] == 5.0  # parsed as text, not the .csv's entry


def test_recorded_dependency_change_invalidates_the_entry(tmp_path):
    (tmp_path / "init.csv").write_text("1")
    extra = tmp_path / "extra.txt"
    extra.write_text("10")
    args = dict(named=["init=" + str(tmp_path / "init.csv")], overrides=[f"parse.extra={extra}"])
    assert run(tmp_path, PARSE, **args).values[("parse", "value")].get()["v"][0] == 11.0
    recorder = Recorder()
    run(tmp_path, PARSE, recorder=recorder, **args)
    assert statuses(recorder)["parse"] == "cached"
    extra.write_text("20")
    recorder = Recorder()
    assert run(tmp_path, PARSE, recorder=recorder, **args).values[("parse", "value")].get()["v"][0] == 21.0
    assert statuses(recorder)["parse"] == "ran"


# -- what publishing may replace --------------------------------------------------------------


@pytest.mark.parametrize("layout", ["user folder", "user file", "file in published folder"])
def test_out_never_replaces_user_files(tmp_path, layout):
    out = tmp_path / "out"
    if layout == "file in published folder":
        run(tmp_path)
        (out / "table" / "notes.txt").write_text("mine")
    elif layout == "user folder":
        (out / "table").mkdir(parents=True)
        (out / "table" / "data.csv").write_text("mine")
    else:
        out.mkdir()
        (out / "table").write_text("mine")
    entries_before = len(list(CacheStore(tmp_path / "cache").iter_entries()))
    with pytest.raises(ConfigError) as info:
        run(tmp_path, overrides=["table.note=changed"])
    assert "table" in str(info.value) and "--out" in str(info.value)
    assert len(list(CacheStore(tmp_path / "cache").iter_entries())) == entries_before  # nothing ran
    mine = {
        "user folder": out / "table" / "data.csv",
        "user file": out / "table",
        "file in published folder": out / "table" / "notes.txt",
    }[layout]
    assert mine.read_text() == "mine"


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


@pytest.mark.subprocess
def test_leftovers_of_a_killed_publish_are_removed(tmp_path):
    """What a killed publish leaves (its marked temporary and replaced folders, or a replaced
    folder renamed away before its marker was written) is removed by the next run and by
    `runner cache gc --out`."""
    out = tmp_path / "out"
    run(tmp_path)
    pid = _dead_pid()
    marker = json.dumps({"tool": publish.TOOL, "stage": "table", "pid": pid, "host": socket.gethostname()})
    for name in (f".table.{pid}.old", f".table.{pid}.tmp"):
        (out / name).mkdir()
        (out / name / "sums.json").write_text("[]")
        (out / name / publish.MARKER).write_text(marker)
    run(tmp_path)
    assert sorted(p.name for p in out.iterdir()) == ["table"]
    shutil.copytree(out / "table", out / f".table.{pid}.old")  # renamed away, not marked yet
    done = CliRunner().invoke(cli, ["cache", "gc", "--cache-dir", str(tmp_path / "cache"), "--out", str(out)])
    assert done.exit_code == 0 and "1 leftover output folders" in done.output
    assert sorted(p.name for p in out.iterdir()) == ["table"]


@pytest.mark.subprocess
def test_user_folders_named_like_leftovers_are_kept(tmp_path):
    """Hidden folders named ``.<name>.<digits>.old`` / ``.tmp`` that no publish of this tool
    wrote (no marker, no manifest of the stage) are a user's: a run and `cache gc` keep them."""
    out = tmp_path / "out"
    pid = _dead_pid()
    mine = {".backup.2023.old": "thesis.txt", f".table.{pid}.tmp": "draft.json", f".table.{pid}.old": "notes.txt"}
    for folder, name in mine.items():
        (out / folder).mkdir(parents=True)
        (out / folder / name).write_text("mine")
    (out / f".table.{pid}.old" / publish.MARKER).write_text(json.dumps({"tool": "another tool", "pid": pid}))
    run(tmp_path)
    done = CliRunner().invoke(cli, ["cache", "gc", "--cache-dir", str(tmp_path / "cache"), "--out", str(out)])
    assert done.exit_code == 0 and "0 leftover output folders" in done.output
    for folder, name in mine.items():
        assert (out / folder / name).read_text() == "mine"


# -- failures -----------------------------------------------------------------------------


def test_disk_full_names_the_stage_and_the_file(tmp_path, monkeypatch):
    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(outputs.np, "savez", full)
    with pytest.raises(StageFailed) as info:
        run(tmp_path)
    message = str(info.value)
    assert "'sums'" in message and "sums.npz" in message and "No space left on device" in message


def test_out_that_cannot_be_written_is_refused_before_anything_runs(tmp_path):
    (tmp_path / "a-file").write_text("not a folder")
    with pytest.raises(ConfigError) as info:
        run(tmp_path, out=tmp_path / "a-file" / "out")
    assert "--out" in str(info.value) and "cannot write there" in str(info.value)
    assert list(CacheStore(tmp_path / "cache").iter_entries()) == []


@pytest.mark.parametrize("where", ["root", "home", "project", "project folder"])
def test_out_at_a_root_the_home_folder_or_the_project_is_refused(tmp_path, monkeypatch, where):
    """--out /, the home folder itself and the project's own folders are refused before
    anything runs, and nothing is written there."""
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    repo = Path(publish.__file__).resolve().parents[1]
    out = {"root": Path("/"), "home": home, "project": repo, "project folder": repo / "fixtures" / "x"}[where]
    before = sorted(p.name for p in out.iterdir()) if out.exists() else None
    with pytest.raises(ConfigError) as info:
        run(tmp_path, out=out)
    [issue] = info.value.issues
    assert str(issue).startswith(f"--out: {out}: is ") and "choose a folder of its own" in str(issue)
    assert (sorted(p.name for p in out.iterdir()) if out.exists() else None) == before
    assert list(CacheStore(tmp_path / "cache").iter_entries()) == []


def test_a_user_folder_in_out_is_refused_naming_it_once(tmp_path):
    """A folder of the user's at a stage's place in --out: one line naming that folder (not
    --out again) and the stage, nothing run."""
    (tmp_path / "out" / "table").mkdir(parents=True)
    with pytest.raises(ConfigError) as info:
        run(tmp_path)
    assert [str(issue) for issue in info.value.issues] == [
        f"--out: {tmp_path / 'out' / 'table'}: exists without a manifest.json of runner; "
        "stage 'table' publishes there (move it away or choose another --out)"
    ]
    assert list(CacheStore(tmp_path / "cache").iter_entries()) == []


def test_out_beside_the_project_folders_is_accepted(tmp_path):
    assert publish.refused(tmp_path / "out") is None
    assert publish.refused(Path(publish.__file__).resolve().parents[1] / "out") is None


def test_disk_full_while_publishing_names_the_destination_and_cleans_up(tmp_path, monkeypatch):
    """A full --out disk while a file is copied: the error names the file written under --out,
    and no temporary folder is left there."""
    real = open

    class Full:
        def __init__(self, file):
            self.file = file

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.file.close()

        def fileno(self):
            return self.file.fileno()

        def write(self, block):
            raise OSError(errno.ENOSPC, "No space left on device")

    def opening(path, mode="r", *args, **kwargs):
        file = real(path, mode, *args, **kwargs)
        return Full(file) if "w" in mode and str(tmp_path / "out") in str(path) else file

    monkeypatch.setattr(outputs, "open", opening, raising=False)
    monkeypatch.setattr(outputs, "FICLONE", 0)  # no clone: the bytes are copied
    with pytest.raises(StageFailed) as info:
        run(tmp_path)
    message = str(info.value)
    assert "'table'" in message and "No space left on device" in message
    assert f"{tmp_path / 'out'}/" in message and str(tmp_path / "cache") not in message
    assert list((tmp_path / "out").iterdir()) == []
