"""Expression states reach the target, end to end, on real-texture clips with known expression.

``lab/realface`` renders the astronaut photo's face holding each state in turn (its
``states`` script) and alternating shut eyes with an open mouth so that no frame is a neutral
face (``no_neutral``); the truth knows every frame's expression. The default pipeline runs on
each through the CLI, as a user runs it. The landmarker reads this synthetic face's blinks, wide
eyes, open mouth, smile, pucker and brow raise, but not its brow furrow or lip press (measured:
docs/realface.md, "States"); those two are covered where the geometry enters the mapping
(tests/stages/geometry/test_mapping.py, test_states.py).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stages.geometry.states import SEALED_GAP, state_signals
from tests.test_end_to_end import run_cli

pytestmark = [pytest.mark.slow, pytest.mark.subprocess]

SIZE = 256


def run(folder: Path, script: str, seed: int) -> tuple[dict, dict, dict]:
    """The clip of ``script``, the default pipeline on it; its truth, data file and the target's
    and performer's state signals."""
    from lab.realface.clip import make_clip

    clip, truth = make_clip(folder, frames=0, seed=seed, size=SIZE, script=script)
    result = run_cli(
        "run", "pipeline.yaml", "--in", str(clip), "--out", str(folder / "out"), "--cache-dir", str(folder / "cache")
    )
    assert result.returncode == 0, result.stderr
    data = dict(np.load(folder / "out" / "data" / "data.npz"))
    names = [str(n) for n in data["target_names"]]
    signals = {"target": state_signals(data["target_xy"], names), "performer": state_signals(data["tracked_xy"], names)}
    return dict(np.load(truth)), data, signals


def held(truth: dict, state: str) -> np.ndarray:
    """The frames where the truth holds ``state`` at full strength."""
    spans = [(a, b) for n, (a, b) in zip(truth["state_names"], truth["state_spans"]) if n == state]
    return np.concatenate([np.arange(a, b + 1) for a, b in spans])


@pytest.fixture(scope="module")
def no_neutral(tmp_path_factory):
    return run(tmp_path_factory.mktemp("no_neutral"), "no_neutral", seed=4)


@pytest.fixture(scope="module")
def states(tmp_path_factory):
    return run(tmp_path_factory.mktemp("states"), "states", seed=3)


def test_a_clip_without_a_neutral_frame_still_shuts_and_opens_the_targets_eyes(no_neutral):
    """Whenever the eyes are open the mouth is open, and whenever it is closed the eyes are shut: a
    single reference frame would make one of them the target's rest. The neutral estimated region
    by region gives the target shut eyes in every blink and open eyes and mouth in every opening."""
    truth, data, signals = no_neutral
    target = signals["target"]
    assert bool(data.get("pose_neutral_frame") is not None)
    blink, opening = held(truth, "blink"), held(truth, "jaw_open")
    for side in "lr":  # the landmarker reads this face's shut lids at 0.27-0.34 of their open gap
        open_level = np.percentile(target[f"eye_open_{side}"][opening], 90)
        assert (target[f"eye_open_{side}"][blink] < 0.45 * open_level).all(), side
    assert (target["mouth_open"][opening] > 0.1).all()
    assert (target["mouth_open"][blink] < 0.6 * target["mouth_open"][opening].mean()).all()


def test_each_state_the_landmarker_reads_reaches_the_target(states):
    """Against the clip's own rest frames: both eyes shut in the blink; the winked eye less open
    than the other; wider eyes; an open mouth; a wider mouth in the smile, a narrower one in the
    pucker and the "O" (open as well); brows higher in the raise; and lips sealed wherever the
    performer's are."""
    truth, data, signals = states
    target, performer = signals["target"], signals["performer"]
    rest = np.flatnonzero(truth["expression"].max(axis=1) < 0.02)
    level = {k: np.median(target[k][rest]) for k in target}

    def mean(key: str, state: str) -> float:
        return float(np.mean(target[key][held(truth, state)]))

    for side in "lr":
        assert mean(f"eye_open_{side}", "blink") < 0.45 * level[f"eye_open_{side}"], side
        assert mean(f"eye_open_{side}", "wide") > 1.08 * level[f"eye_open_{side}"], side
    assert mean("eye_open_l", "wink_l") < 0.8 * mean("eye_open_r", "wink_l")
    assert mean("eye_open_r", "wink_r") < 0.8 * mean("eye_open_l", "wink_r")
    assert mean("mouth_open", "jaw_open") > level["mouth_open"] + 0.1
    assert mean("mouth_width", "smile") > 1.08 * level["mouth_width"]
    assert mean("mouth_width", "pucker") < 0.93 * level["mouth_width"]
    assert mean("mouth_width", "o_mouth") < 0.96 * level["mouth_width"]  # narrower though open
    assert mean("mouth_open", "o_mouth") > level["mouth_open"] + 0.1
    assert mean("brow_raise", "brow_raise") > level["brow_raise"] + 0.04
    sealed = performer["mouth_open"] < SEALED_GAP
    assert ((target["mouth_open"] < SEALED_GAP) == sealed).mean() >= 0.95
