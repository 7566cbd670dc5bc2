"""Every YAML file the tool reads (pipeline, batch manifest, pack manifest, layout, the
editor's pack) refuses, with ``file:line:column``: collections nested 100,000 deep (PyYAML's
recursion), bytes that are not UTF-8, and a key given twice (PyYAML keeps the last silently)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from runner.config import ConfigError, load_pipeline
from runner.registry import Registry
from stages.actor_pack import PackError, load_pack
from stages.layout import load_layout
from tests.runner.helpers import REPO, run_cli

PACK = REPO / "fixtures" / "packs" / "target"
DEEP = "[" * 100_000 + "]" * 100_000 + "\n"


def pipeline_text(extra: str) -> str:
    return "inputs: {clip: {type: video}}\n" + extra + "stages:\n  decode: {uses: video.decode, inputs: {video: clip}}\n"


def write(path: Path, content: str | bytes) -> Path:
    path.write_bytes(content.encode() if isinstance(content, str) else content)
    return path


def issue_lines(exc: ConfigError) -> list[str]:
    return [str(issue) for issue in exc.issues]


@pytest.mark.parametrize("case", ["deep", "latin1", "duplicate"])
def test_pipeline_refuses_with_position(tmp_path, case):
    base = pipeline_text("")
    text = {
        "deep": "chunk_frames: " + DEEP + base,
        "latin1": base.encode() + b"# caf\xe9\n",
        "duplicate": base.replace("inputs: {clip", "chunk_frames: 4\nchunk_frames: 8\ninputs: {clip"),
    }[case]
    path = write(tmp_path / "p.yaml", text)
    with pytest.raises(ConfigError) as info:
        load_pipeline(path, Registry.from_entry_points())
    # the 64th '[' after 'chunk_frames: ' (14 columns) opens the 65th collection
    expected = {
        "deep": f"{path}:1:{14 + 64}: yaml: nested deeper than 64 levels",
        "latin1": f"{path}:4:6: yaml: not UTF-8 text (byte 0xe9: invalid continuation byte)",
        "duplicate": f"{path}:2:1: yaml: duplicate key 'chunk_frames' (first at line 1, column 1)",
    }[case]
    assert issue_lines(info.value) == [expected]


@pytest.mark.subprocess
def test_cli_exit_2_one_line_no_traceback(tmp_path, env):
    for name, content in (("deep.yaml", "chunk_frames: " + DEEP), ("latin1.yaml", b"stages:\n  caf\xe9: {}\n")):
        path = write(tmp_path / name, content)
        result = run_cli("run", path, "--dry-run", env=env, cwd=tmp_path)
        assert result.returncode == 2, result.stderr
        assert result.stderr.count("\n") == 1 and result.stderr.startswith(f"error: {path}:")
        assert "Traceback" not in result.stderr


@pytest.mark.parametrize("case", ["deep", "latin1", "duplicate"])
def test_batch_manifest_refuses_with_position(tmp_path, case):
    from runner.batch_manifest import load_manifest

    base = f"defaults: {{pipeline: {REPO / 'pipeline.yaml'}}}\njobs:\n  a: {{clip: {REPO / 'fixtures/clips/calm.mp4'}}}\n"
    text = {
        "deep": base + "  b: " + DEEP,
        "latin1": base.encode() + b"  caf\xe9: {}\n",
        "duplicate": base + f"  a: {{clip: {REPO / 'fixtures/clips/live.mp4'}}}\n",
    }[case]
    path = write(tmp_path / "shots.yaml", text)
    with pytest.raises(ConfigError) as info:
        load_manifest(path, Registry.from_entry_points())
    # under the top mapping and `jobs`, the 63rd '[' after '  b: ' (5 columns) opens the 65th
    expected = {
        "deep": f"{path}:4:{5 + 63}: yaml: nested deeper than 64 levels",
        "latin1": f"{path}:4:6: yaml: not UTF-8 text (byte 0xe9: invalid continuation byte)",
        "duplicate": f"{path}:4:3: yaml: duplicate key 'a' (first at line 3, column 3)",
    }[case]
    assert issue_lines(info.value) == [expected]


@pytest.mark.parametrize("case", ["deep", "latin1", "duplicate"])
def test_pack_manifest_refuses_with_position(tmp_path, case):
    pack = tmp_path / "pack"
    shutil.copytree(PACK, pack)
    manifest = pack / "pack.yaml"
    text = manifest.read_text()
    lines = text.count("\n")
    content = {
        "deep": text + "notes: " + DEEP,
        "latin1": text.encode() + b"notes: caf\xe9\n",
        "duplicate": text + "neutral: {name: neutral, image: images/cap00.png, points: points/cap00.csv}\n",
    }[case]
    write(manifest, content)
    with pytest.raises(PackError) as info:
        load_pack(pack)
    expected = {
        "deep": f"{manifest}:{lines + 1}:{7 + 64}: not valid YAML (nested deeper than 64 levels)",
        "latin1": f"{manifest}:{lines + 1}:11: not valid YAML (not UTF-8 text",
        "duplicate": f"{manifest}:{lines + 1}:1: not valid YAML (duplicate key 'neutral' (first at line ",
    }[case]
    assert expected in str(info.value) and "\n" not in str(info.value)


def test_layout_file_refuses_duplicate_keys(tmp_path):
    layout = tmp_path / "layout.yaml"
    bundled = (REPO / "stages" / "layouts" / "zhang134.yaml").read_text()
    write(layout, "name: first\n" + bundled)
    with pytest.raises(Exception) as info:
        load_layout(layout)
    assert f"{layout}:" in str(info.value) and "duplicate key 'name' (first at line 1, column 1)" in str(info.value)


@pytest.mark.subprocess
def test_editor_refuses_a_bad_pack_manifest_with_exit_2(tmp_path):
    pack = tmp_path / "pack"
    shutil.copytree(PACK, pack)
    write(pack / "pack.yaml", (pack / "pack.yaml").read_bytes() + b"notes: caf\xe9\n")
    result = subprocess.run(
        [sys.executable, "-m", "editor.cli", "--pack", str(pack)], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 2, result.stderr
    assert f"{pack / 'pack.yaml'}:" in result.stderr and "not UTF-8" in result.stderr
    assert "Traceback" not in result.stderr
