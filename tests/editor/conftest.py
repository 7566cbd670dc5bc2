"""The editor as a user starts it (``python -m editor.cli``) on the bundled 240x320 target pack
(the ``browser`` fixture is the session's, in ``tests/conftest.py``)."""

from __future__ import annotations

import os
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from editor.cli import spawn

REPO = Path(__file__).resolve().parents[2]
PACK = REPO / "fixtures" / "packs" / "target"


@dataclass(frozen=True)
class Editor:
    url: str      # the page, with its token
    base: str     # http://host:port
    token: str
    process: subprocess.Popen


def start_editor(pack: Path, *options: str) -> Editor:
    process, url = spawn(pack, *options)
    base, _, token = url.partition("/?token=")
    return Editor(url, base, token, process)


def stop_editor(editor: Editor) -> None:
    editor.process.terminate()
    try:
        editor.process.wait(timeout=10)
    except subprocess.TimeoutExpired:
        editor.process.kill()


@pytest.fixture(scope="session")
def performance(tmp_path_factory) -> Path:
    """A run's data.npz stand-in: five of the pack's captured geometries as frames."""
    from stages.actor_pack import load_pack

    pack = load_pack(PACK)
    path = tmp_path_factory.mktemp("run") / "data.npz"
    np.savez(path, target_xy=pack.captured_points[:5], target_names=np.array(pack.layout.point_names))
    return path


@pytest.fixture(scope="session")
def editor_server(performance):
    editor = start_editor(PACK, "--performance", str(performance))
    yield editor
    stop_editor(editor)
