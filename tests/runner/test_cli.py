"""End-to-end runs of the `runner` CLI in a subprocess on the tiny fixture clip."""

from __future__ import annotations

import contextlib
import importlib.metadata
import io
import json
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import av
import numpy as np
import pytest

from runner.cache import CacheStore
from runner.cli import main
from stages.color import luma_opencv
from stages.video import VideoDecode
from tests.runner.helpers import DATA, REPO, TINY, chunk_status, read_log, run_cli, stage_status, tree_bytes

GRAPH = DATA / "graph.yaml"
CHAIN = DATA / "chain.yaml"


def _decoded(path: Path) -> np.ndarray:
    with av.open(str(path)) as container:
        return np.stack([f.to_ndarray(format="rgb24") for f in container.decode(video=0)])


@pytest.mark.subprocess
def test_chain_runs_end_to_end_and_reruns_from_cache(env, tmp_path):
    out = tmp_path / "out"
    first = run_cli("run", CHAIN, "--in", TINY, "--out", out, "--log-json", tmp_path / "1.jsonl", env=env, cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    assert stage_status(read_log(tmp_path / "1.jsonl")) == {"decode": "on demand", "gray": "ran", "write": "ran"}
    # The published video is the grayscale of the clip (H.264 at crf 18: close, not exact).
    video = _decoded(out / "write" / "video.mp4")
    truth = luma_opencv(VideoDecode().process(0, 48, {"video": TINY}, {}, None)["frames"])
    assert video.shape == (48, 120, 160, 3)
    assert np.abs(video[..., 1].astype(int) - truth).mean() < 2.0
    manifest = json.loads((out / "write" / "manifest.json").read_text())
    assert [f["path"] for f in manifest["files"]] == ["video.mp4"]
    # One summary line per stage on stdout; gray was computed while write encoded it (gray's
    # producer thread may have computed all 3 chunks, within the broadcast's keep, before write's
    # turn came: write then read them held, with gray's digests known).
    lines = first.stdout.splitlines()
    assert [line.split()[0] for line in lines[:3]] == ["decode", "gray", "write"]
    assert "0/3 chunks cached  48 frames" in lines[1] and "(computed while write read it)" in lines[1]
    assert lines[2].split()[2] == "ran" and lines[2].endswith(("s", "(read gray while it was computed)"))

    second = run_cli("run", CHAIN, "--in", TINY, "--out", out, "--log-json", tmp_path / "2.jsonl", env=env, cwd=tmp_path)
    assert second.returncode == 0, second.stderr
    assert stage_status(read_log(tmp_path / "2.jsonl")) == {"decode": "on demand", "gray": "cached", "write": "cached"}

    # A published file damaged by hand is restored from the cache by the next run.
    published = (out / "write" / "video.mp4").read_bytes()
    (out / "write" / "video.mp4").write_bytes(b"truncated")
    third = run_cli("run", CHAIN, "--in", TINY, "--out", out, env=env, cwd=tmp_path)
    assert third.returncode == 0, third.stderr
    assert (out / "write" / "video.mp4").read_bytes() == published


@pytest.mark.subprocess
def test_param_change_reruns_only_stages_whose_inputs_changed(env, tmp_path):
    def run(name: str, *sets: str) -> dict[str, str]:
        args = [a for s in sets for a in ("--set", s)]
        done = run_cli("run", GRAPH, "--out", tmp_path / "out", "--log-json", tmp_path / name, *args, env=env, cwd=tmp_path)
        assert done.returncode == 0, done.stderr
        return stage_status(read_log(tmp_path / name))

    assert set(run("a")) == {"decode", "add", "gray", "write", "mean", "table"}
    # `note` changes add's key but not its bytes: add re-runs, everything downstream is a hit.
    assert run("b", "add.note=x") == {
        "decode": "on demand",
        "add": "ran",
        "gray": "cached",
        "write": "cached",
        "mean": "cached",
        "table": "cached",
    }
    # `value` changes add's output: add, gray and write re-run; the other branch does not.
    assert run("c", "add.value=11") == {
        "decode": "on demand",
        "add": "ran",
        "gray": "ran",
        "write": "ran",
        "mean": "cached",
        "table": "cached",
    }
    assert run("d", "add.value=11", "table.digits=2") == {
        "decode": "on demand",
        "add": "cached",
        "gray": "cached",
        "write": "cached",
        "mean": "cached",
        "table": "ran",
    }
    # A change confined to the first chunk of add's output re-runs only that chunk downstream.
    assert run("e", "add.value=11", "table.digits=2", "add.start_at=2")["gray"] == "partial"
    assert chunk_status(read_log(tmp_path / "e"), "gray") == {
        (0, 8): "ran",
        (8, 16): "cached",
        (16, 24): "cached",
        (24, 32): "cached",
        (32, 40): "cached",
        (40, 48): "cached",
    }
    assert json.loads((tmp_path / "out" / "table" / "series.json").read_text())[0] == pytest.approx(
        VideoDecode().process(0, 1, {"video": TINY}, {}, None)["frames"].mean(), abs=0.01
    )


@pytest.mark.subprocess
def test_dry_run_reports_reasons_and_runs_nothing(env, tmp_path):
    out, cache = tmp_path / "out", Path(env["RUNNER_CACHE_DIR"])
    fresh = run_cli("run", GRAPH, "--out", out, "--dry-run", env=env, cwd=tmp_path)
    assert fresh.returncode == 0, fresh.stderr
    lines = {line.split()[0]: line for line in fresh.stdout.splitlines()[1:]}
    assert "will run" in lines["add"] and "never run" in lines["add"] and "0/6 chunks cached" in lines["add"]
    assert "may run" in lines["gray"] and "after add" in lines["gray"]
    assert not out.exists()
    assert not any(e.record.get("outputs") for e in CacheStore(cache).iter_entries())

    assert run_cli("run", GRAPH, "--out", out, env=env, cwd=tmp_path).returncode == 0
    before = sorted(e.key for e in CacheStore(cache).iter_entries())
    changed = run_cli("run", GRAPH, "--out", out, "--dry-run", "--set", "add.value=3", "--force", "table", env=env, cwd=tmp_path)
    lines = {line.split()[0]: line for line in changed.stdout.splitlines()[1:]}
    assert "will run" in lines["add"] and "param value: 10 -> 3" in lines["add"]
    assert "may run" in lines["write"]
    assert "cached" in lines["mean"] and "forced" in lines["table"]
    assert sorted(e.key for e in CacheStore(cache).iter_entries()) == before


@pytest.mark.subprocess
def test_until_and_force(env, tmp_path):
    log = tmp_path / "until.jsonl"
    done = run_cli("run", GRAPH, "--out", tmp_path / "out", "--until", "mean", "--log-json", log, env=env, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert stage_status(read_log(log)) == {"decode": "on demand", "mean": "ran"}
    assert not (tmp_path / "out").exists()
    run_cli("run", GRAPH, "--out", tmp_path / "out", env=env, cwd=tmp_path)
    published = tree_bytes(tmp_path / "out" / "write")
    log = tmp_path / "force.jsonl"
    done = run_cli("run", GRAPH, "--out", tmp_path / "out", "--force", "add", "--log-json", log, env=env, cwd=tmp_path)
    # Forcing add recomputes it; its bytes are the same, so downstream stays cached.
    assert stage_status(read_log(log))["add"] == "ran" and stage_status(read_log(log))["gray"] == "cached"
    assert tree_bytes(tmp_path / "out" / "write") == published


@pytest.mark.subprocess
@pytest.mark.parametrize(
    "content, words",
    [
        (None, "no such file"),
        (b"this is not a video\n" * 20, "not a readable video"),
    ],
)
def test_bad_clip_is_one_line_error(env, tmp_path, content, words):
    clip = tmp_path / "clip.mp4"
    if content is not None:
        clip.write_bytes(content)
    done = run_cli("run", CHAIN, "--in", clip, "--out", tmp_path / "out", env=env, cwd=tmp_path)
    expected_code = 2 if content is None else 1  # a missing input is caught before anything runs
    assert done.returncode == expected_code
    assert len(done.stderr.strip().splitlines()) == 1 and "Traceback" not in done.stderr
    assert str(clip) in done.stderr and words in done.stderr


@pytest.mark.subprocess
def test_a_bundle_without_a_declared_field_fails_its_stage_in_one_line(env, tmp_path):
    pipeline = tmp_path / "typed.yaml"
    pipeline.write_text(
        f"inputs:\n  clip: {{type: video, default: {TINY}}}\n"
        "stages:\n"
        "  decode: {uses: video.decode, inputs: {video: clip}}\n"
        "  mean: {uses: test.typed_mean, params: {drop: frame}, inputs: {frames: decode.frames}}\n"
    )
    done = run_cli("run", pipeline, "--out", tmp_path / "out", env=env, cwd=tmp_path)
    assert done.returncode == 1
    assert done.stderr.strip().splitlines() == [
        f"error: stage 'mean' (test.typed_mean): output 'series' (series): field 'frame' is missing [{TINY}]"
    ]
    kept = run_cli("run", pipeline, "--set", "mean.drop=", "--out", tmp_path / "out", env=env, cwd=tmp_path)
    assert kept.returncode == 0, kept.stderr


def cli_main(*args: str | Path) -> tuple[int, str, str]:
    """Run ``runner ARGS`` in this process: exit code, stdout, stderr (errors found before
    anything runs need no subprocess)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), pytest.raises(SystemExit) as info:
        main([str(a) for a in args])
    return info.value.code, out.getvalue(), err.getvalue()


def test_version_is_the_installed_package_version():
    code, out, err = cli_main("--version")
    assert (code, out, err) == (0, f"runner {importlib.metadata.version('expression-mapping')}\n", "")
    with open(REPO / "pyproject.toml", "rb") as f:
        assert importlib.metadata.version("expression-mapping") == tomllib.load(f)["project"]["version"]


def test_config_errors_exit_2_with_positions(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("RUNNER_CACHE_DIR", str(tmp_path / "cache"))
    bad = tmp_path / "bad.yaml"
    bad.write_text("stages:\n  a:\n    uses: no.such\n  b:\n    uses: image.gray\n    inputs: {frames: a.frames}\n")
    code, _, err = cli_main("run", bad)
    assert code == 2
    assert err.splitlines() == [
        f"error: {bad}:3:11: stages.a.uses: unknown stage 'no.such' (see `runner stages`)",
        f"error: {bad}:6:22: stages.b.inputs.frames: missing input: no stage named 'a'",
    ]
    assert cli_main("run", CHAIN, "--set", "write.crf=high")[0] == 2
    code, _, err = cli_main("run", CHAIN, "--set", "write.crf=100")
    assert code == 2 and err == "error: --set: write.crf: out of range: expected 0 <= crf <= 51, got 100\n"
    assert cli_main("run", CHAIN, "--until", "nope")[0] == 2
    assert cli_main("run", CHAIN, "--jobs", "0")[0] == 2
    if importlib.metadata.version("torch").endswith("+cpu"):
        code, _, err = cli_main("run", CHAIN, "--device", "cuda")
        assert code == 2 and "CUDA is not available" in err
    bad.write_text("stages:\n  a:\n    uses: !!python/object/apply:os.system ['echo owned']\n")
    code, out, err = cli_main("run", bad)
    assert code == 2 and "owned" not in out
    assert err == f"error: {bad}:3:11: yaml: tag 'tag:yaml.org,2002:python/object/apply:os.system' is not allowed\n"
    assert not (tmp_path / "cache").exists()


def test_an_error_quoting_a_long_value_is_one_line_of_bounded_length(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("RUNNER_CACHE_DIR", str(tmp_path / "cache"))
    code, _, err = cli_main("run", CHAIN, "--until", "x" * 100_000)
    assert code == 2 and err.startswith("error: --until: xxx") and err.endswith(" more characters)\n")
    assert len(err.splitlines()) == 1 and len(err) < 500
    code, _, err = cli_main("run", CHAIN, "--set", f"write.crf={'9' * 5000}")
    assert code == 2 and err == f"error: --set: write.crf: wrong type: expected int, got '{'9' * 79}... (5002 characters)\n"


@pytest.mark.parametrize("days", ["nan", "inf", "-1"])
def test_cache_gc_refuses_days_that_are_not_a_finite_number_of_zero_or_more(tmp_path, days):
    entry = tmp_path / "cache" / "entries" / "ab" / "cd"
    entry.mkdir(parents=True)
    code, out, err = cli_main("cache", "gc", "--older-than", days, "--cache-dir", tmp_path / "cache", "--out", tmp_path / "o")
    assert code == 2 and out == "" and "Invalid value for '--older-than'" in err
    assert entry.is_dir() and not (tmp_path / "o").exists()


def test_the_dry_run_of_a_run_into_the_filesystem_root_is_refused_as_the_run_is(tmp_path):
    code, out, err = cli_main("run", CHAIN, "--out", "/", "--dry-run", "--cache-dir", tmp_path / "cache")
    assert (
        code == 2
        and out == ""
        and err
        == "error: --out: /: is the filesystem root: a run writes one folder per stage there (choose a folder of its own)\n"
    )


def test_a_head_pose_wired_to_a_stage_that_reads_the_other_one_fails_at_load(tmp_path, monkeypatch):
    """pose.pnp's pose is absolute (tvec mm, with its camera), compensate.rigid3d's relative to the
    head frame (tvec px, a scale): each reader takes one of them, checked before anything runs."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("RUNNER_CACHE_DIR", str(tmp_path / "cache"))
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        "inputs: {clip: {type: video}, first: {type: file}, target: {type: dir}}\n"
        "stages:\n"
        "  decode: {uses: video.decode, inputs: {video: clip}}\n"
        "  track: {uses: track.correlation, inputs: {frames: decode.frames, init: first}}\n"
        "  marks: {uses: landmarks.mediapipe, inputs: {frames: decode.frames}}\n"
        "  pack: {uses: pack.load, inputs: {pack: target}}\n"
        "  pnp: {uses: pose.pnp, inputs: {points: track.points, layout: pack.layout, model3d: pack.model3d, camera: pack.camera}}\n"
        "  rigid: {uses: compensate.rigid3d, inputs: {points: track.points, landmarks: marks.landmarks}}\n"
        "  head:\n"
        "    uses: render3d.head\n"
        "    inputs: {geometry: pack.geometry, model3d: pack.model3d, camera: pack.camera, pose: pnp.pose}\n"
        "  front: {uses: compensate.pose3d, inputs: {points: track.points, model3d: pack.model3d, pose: rigid.pose}}\n"
    )
    lines = bad.read_text().splitlines()
    head, front = lines[10].index("pnp.pose") + 1, lines[11].index("rigid.pose") + 1  # 1-based columns
    code, _, err = cli_main("run", bad)
    assert code == 2
    assert err.splitlines() == [
        f"error: {bad}:11:{head}: stages.head.inputs.pose: port type mismatch: 'pose' takes pose_relative, pnp.pose gives pose_pnp",
        f"error: {bad}:12:{front}: stages.front.inputs.pose: port type mismatch: 'pose' takes pose_pnp, rigid.pose gives pose_relative",
    ]
    assert not (tmp_path / "cache").exists()


@pytest.mark.subprocess
def test_stages_dag_and_cache_commands(env, tmp_path):
    listed = run_cli("stages", env=env, cwd=tmp_path)
    assert listed.returncode == 0
    assert "video.decode" in listed.stdout and "param crf: int = 18" in listed.stdout
    mermaid = run_cli("dag", GRAPH, "--mermaid", env=env, cwd=tmp_path).stdout
    assert mermaid.startswith("flowchart LR") and 'st_add -->|"frames → frames"| st_gray' in mermaid
    dot = run_cli("dag", GRAPH, "--dot", env=env, cwd=tmp_path).stdout
    assert '"decode" -> "mean"' in dot
    run_cli("run", CHAIN, "--jobs", "2", "--out", tmp_path / "out", env=env, cwd=tmp_path)
    ls = run_cli("cache", "ls", env=env, cwd=tmp_path).stdout
    assert "chunk 0-16" in ls and "5 entries" in ls  # 3 gray chunks, decode's stream info, write
    assert "removed 5 entries" in run_cli("cache", "clear", env=env, cwd=tmp_path).stdout
    assert "0 entries" in run_cli("cache", "ls", env=env, cwd=tmp_path).stdout


def test_a_swallowed_interrupt_is_not_reported_but_other_unraisables_are(capsys, monkeypatch):
    """A KeyboardInterrupt raised by the signal handler inside a callback (an import lock's
    weakref callback, seen in a CI run) is unraisable: the run stops at its next event instead
    (exit 130), so it must not print "Exception ignored"; other unraisable errors still do."""
    import gc
    import sys

    from runner import signals

    class Raises:
        def __init__(self, error: BaseException):
            self.error = error

        def __del__(self):
            raise self.error

    monkeypatch.setattr(sys, "unraisablehook", signals.unraisable)
    Raises(KeyboardInterrupt())
    gc.collect()
    assert "Exception ignored" not in capsys.readouterr().err
    Raises(ValueError("boom"))
    gc.collect()
    assert "boom" in capsys.readouterr().err


@pytest.mark.subprocess
def test_exit_now_waits_for_threads_and_flushes(tmp_path):
    """The command's fast exit (no interpreter teardown) keeps the exit status, what was printed
    without a newline, and the work of a thread still running."""
    marker = tmp_path / "written"
    script = (
        "import sys, threading, time; from pathlib import Path; from runner.signals import exit_now\n"
        "def late(): time.sleep(0.3); Path(sys.argv[1]).write_text('done')\n"
        "threading.Thread(target=late).start(); print('partial', end=''); exit_now(3)"
    )
    done = subprocess.run(
        [sys.executable, "-c", script, str(marker)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=Path(__file__).resolve().parents[2],
    )
    assert (done.returncode, done.stdout) == (3, "partial")
    assert marker.read_text() == "done"


PACK_PIPELINE = """\
inputs:
  clip: {type: video}
  pack: {type: dir}
stages:
  decode: {uses: video.decode, inputs: {video: clip}}
  load: {uses: pack.load, inputs: {pack: pack}}
"""


@pytest.mark.parametrize(
    ("damage", "words"),
    [
        ("empty_npz", "captured.npz: field 'captured': "),
        ("nan_intrinsics", "pack.yaml: field 'intrinsics[0][0]': expected a finite number, got nan"),
        ("missing_image", "pack.yaml: field 'examples[1].image': file not found: "),
    ],
)
def test_a_bad_pack_is_refused_before_anything_runs(tmp_path, monkeypatch, damage, words):
    """A pack's manifest and the files it names are checked when the inputs are bound
    (``pack.load``'s input check), as the pipeline file is: exit 2, one line naming the file and
    the field, nothing decoded or stored, with or without --dry-run."""
    monkeypatch.chdir(tmp_path)
    pack = tmp_path / "pack"
    shutil.copytree(REPO / "fixtures" / "packs" / "target", pack)
    manifest = pack / "pack.yaml"
    if damage == "empty_npz":
        (pack / "captured.npz").write_bytes(b"")
    elif damage == "nan_intrinsics":
        manifest.write_text(manifest.read_text().replace("[384.000000, 0.000000, 119.500000]", "[.nan, 0, 119.5]"))
    else:
        (pack / "images" / "cap04.png").unlink()
    pipeline = tmp_path / "p.yaml"
    pipeline.write_text(PACK_PIPELINE)
    for dry in ((), ("--dry-run",)):
        code, out, err = cli_main(
            "run", pipeline, "--in", TINY, "--input", f"pack={pack}", "--cache-dir", tmp_path / "cache", *dry
        )
        assert code == 2, err
        assert err.startswith(f"error: {pipeline}:3:3: inputs.pack: wrong input: actor pack {pack}/"), err
        assert words in err and err.count("\n") == 1, err
        assert out == "" and not (tmp_path / "cache").exists()


def test_an_eof_error_of_a_stage_is_not_reported_as_an_interrupt(tmp_path, monkeypatch):
    from runner import execute

    def eof(self):
        raise EOFError("Ran out of input")

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(execute.Runner, "run", eof)
    err = io.StringIO()
    with contextlib.redirect_stderr(err), pytest.raises(EOFError):
        main(["run", str(CHAIN), "--cache-dir", str(tmp_path / "cache")])
    assert "interrupted" not in err.getvalue()


WARNED = """inputs: {clip: {type: video}}
chunk_frames: 8
stages:
  decode: {uses: video.decode, inputs: {video: clip}}
  mean: {uses: test.warn_mean, inputs: {frames: decode.frames}}
  table: {uses: test.table, inputs: {series: mean.series}}
  video: {uses: write.video, params: {crf: 20}, inputs: {frames: decode.frames}}
"""  # `mean` reads a source's frames while `video` computes: it runs in a child process (runner.offload)


@pytest.mark.subprocess
def test_warnings_are_one_line_each_once_and_given_again_by_a_cached_run(env, tmp_path):
    """A stage's own warning and a numpy RuntimeWarning of its computation: one line each on
    stderr (the stage ran in a child process and was then looked up by the run: still once),
    and a fully cached rerun says them again (recorded with the entry)."""
    pipeline = tmp_path / "warned.yaml"
    pipeline.write_text(WARNED)
    expected = [
        "warning: test.warn_mean: the series is made of test frames",
        "warning: overflow encountered in scalar multiply (RuntimeWarning, runner/helpers.py:",
    ]
    for run in ("first", "cached"):
        done = run_cli(
            "run",
            pipeline,
            "--in",
            TINY,
            "--out",
            tmp_path / "out",
            "--log-json",
            tmp_path / f"{run}.jsonl",
            env=env,
            cwd=tmp_path,
        )
        assert done.returncode == 0, done.stderr
        lines = done.stderr.splitlines()
        assert len(lines) == 2 and lines[0] == expected[0] and lines[1].startswith(expected[1]), done.stderr
        assert lines[1].endswith(")") and "RuntimeWarning:" not in done.stderr
        events = read_log(tmp_path / f"{run}.jsonl")
        assert stage_status(events)["mean"] == ("ran" if run == "first" else "cached")
        assert [e["stage"] for e in events if e["event"] == "offload"] == (["mean"] if run == "first" else [])


@pytest.mark.subprocess
def test_a_run_writes_nothing_under_the_home_folder(env, tmp_path):
    """matplotlib keeps its font cache and configuration in the tool's cache, not under $HOME."""
    home = tmp_path / "home"
    home.mkdir()
    env = {k: v for k, v in env.items() if k not in ("MPLCONFIGDIR", "XDG_CACHE_HOME", "XDG_CONFIG_HOME")} | {"HOME": str(home)}
    (tmp_path / "plot.yaml").write_text("stages:\n  plot: {uses: test.plot}\n")
    result = run_cli("run", tmp_path / "plot.yaml", "--out", tmp_path / "out", env=env, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "out" / "plot" / "plot.png").stat().st_size > 0
    assert list(home.iterdir()) == []
    assert any((tmp_path / "cache" / "libraries" / "matplotlib").glob("fontlist-*.json"))
