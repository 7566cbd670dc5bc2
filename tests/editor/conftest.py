"""The editor as a user starts it (``python -m editor.cli``) on the bundled 240x320 target pack
(the ``browser`` fixture is the session's, in ``tests/conftest.py``)."""

from __future__ import annotations

import subprocess
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from editor.cli import spawn

REPO = Path(__file__).resolve().parents[2]
PACK = REPO / "fixtures" / "packs" / "target"


@dataclass(frozen=True)
class Editor:
    url: str  # the page, with its token
    base: str  # http://host:port
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


@pytest.fixture(scope="session")
def pipeline():
    """The target's synthesis model and hierarchical PCA as the pipeline's stages make them."""
    from editor.engine import pack_models

    _, pca, model = pack_models(PACK)
    return model, pca


def synthesize_stage(model, xy: np.ndarray) -> np.ndarray:
    """``synthesis.synthesize`` (the frame stage, default parameters) of geometries (T, N, 2):
    its half-float frames (T, H, W, 3) sRGB."""
    from runner.stage import Context
    from stages.synthesis.synthesize import Synthesize
    from tests.memory_stream import process_once

    stage = Synthesize()
    ctx = Context(device="cpu", files_dir=lambda port: None)
    params = {p.name: p.default for p in stage.params}
    return process_once(stage, 0, len(xy), {"model": model, "points": {"xy": xy}}, params, ctx)["frames"]


def decode(image: bytes) -> np.ndarray:
    """(H, W, 3) uint8 RGB of PNG or JPEG bytes."""
    return cv2.cvtColor(cv2.imdecode(np.frombuffer(image, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def assert_is_pipeline_image(image: np.ndarray, frame: np.ndarray) -> None:
    """``image (H, W, 3)`` uint8 RGB is ``frame`` (the stage's half floats in [0, 1]) in 8 bits:
    the half floats may round to the neighbouring level, rarely."""
    assert image.shape == frame.shape
    difference = np.abs(image.astype(np.float64) - np.round(frame.astype(np.float64) * 255.0))
    assert difference.max() <= 1 and (difference > 0).mean() < 0.01, (difference.max(), (difference > 0).mean())
