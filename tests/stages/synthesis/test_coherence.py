"""Example weights coherent in time (stages.synthesis.coherence): flips averaged away while a
subregion holds still, fast expressions followed frame by frame, chunk-independent results."""

from __future__ import annotations

import numpy as np
import pytest

from runner.stage import Context
from stages.synthesis.build import build_synthesis_model
from stages.synthesis.coherence import coherent_coefficients, window_frames
from stages.synthesis.synthesize import Synthesize
from tests.memory_stream import process_once
from tests.stages.synthesis.synthetic import make_pack

MEMBERS = np.array([[True, True, False], [False, False, True]])  # two subregions over three points


def flipping_clip(n_frames: int = 40, seed: int = 0):
    """Points jittering by 0.1 px whose raw coefficients flip between two examples every frame in
    subregion 0 (the case that popped), and a 3-frame event at frames 20-22: subregion 0's points
    move 10 px and its coefficients go to a third example."""
    rng = np.random.default_rng(seed)
    points = np.zeros((n_frames, 3, 2)) + rng.normal(0, 0.1, (n_frames, 3, 2))
    points[20:23, :2, 1] += 10.0
    raw = np.zeros((n_frames, 2, 3))
    raw[:, 0, 0] = np.arange(n_frames) % 2
    raw[:, 0, 1] = 1 - raw[:, 0, 0]
    raw[20:23, 0] = (0.0, 0.0, 1.0)
    raw[:, 1, 2] = 1.0

    def solve(p: np.ndarray) -> np.ndarray:
        index = [int(np.argmin(np.abs(points - q).sum(axis=(1, 2)))) for q in p]
        return raw[index]

    return points, raw, solve


def test_flips_are_averaged_away_and_events_kept():
    points, raw, solve = flipping_clip()
    out = coherent_coefficients(solve, points, 0, len(points), MEMBERS, sigma_frames=2.0, sigma_px=1.0)
    calm = np.r_[6:14, 28:34]  # away from the event and the clip's ends
    assert np.abs(np.diff(raw[calm, 0, 0])).max() == 1.0
    assert np.abs(np.diff(out[calm, 0, 0])).max() < 0.1  # no pop
    np.testing.assert_allclose(out[20:23, 0], raw[20:23, 0], atol=1e-6)  # the event: its own weights
    assert out[19, 0, 2] < 1e-6 and out[23, 0, 2] < 1e-6  # ... and no lag into the frames around it
    np.testing.assert_allclose(out[:, 1], raw[:, 1])  # a subregion that never changes
    np.testing.assert_allclose(out.sum(axis=2), 1.0)  # convex combinations stay convex
    assert (out >= 0).all()


def test_results_do_not_depend_on_the_chunk():
    points, _, solve = flipping_clip()
    whole = coherent_coefficients(solve, points, 0, 40, MEMBERS, sigma_frames=2.0, sigma_px=1.0)
    pieces = np.concatenate(
        [
            coherent_coefficients(solve, points, a, b, MEMBERS, sigma_frames=2.0, sigma_px=1.0)
            for a, b in ((0, 7), (7, 21), (21, 22), (22, 40))
        ]
    )
    np.testing.assert_array_equal(pieces, whole)
    assert window_frames(2.0) == 6 and window_frames(0.0) == 0
    np.testing.assert_array_equal(
        coherent_coefficients(solve, points, 3, 9, MEMBERS, sigma_frames=0.0, sigma_px=1.0), solve(points[3:9])
    )


@pytest.fixture(scope="module")
def model():
    return build_synthesis_model(make_pack(), band_px=6.0)


def test_the_stage_composites_the_coherent_weights(model, tmp_path):
    """On the synthetic pack, a clip alternating between two examples' geometries blurred to
    0.05 px apart: each frame's own QP alternates between the two, the stage's coefficients do not."""
    pack = make_pack()
    a, b = pack.examples[0].points, pack.examples[1].points
    mid = (a + b) / 2
    frames = np.stack([mid + (0.025 if t % 2 else -0.025) * (b - a) for t in range(24)])
    inputs = {"model": model, "points": {"xy": frames, "valid": np.ones(frames.shape[:2], bool)}}
    ctx = Context(device="cpu", files_dir=lambda port: tmp_path)
    stage = Synthesize()
    params = {p.name: p.default for p in stage.params}
    raw = process_once(stage, 0, 24, inputs, params | {"coherence_frames": 0.0}, ctx)["coeffs"]["coeffs"]
    smooth = process_once(stage, 0, 24, inputs, params, ctx)["coeffs"]["coeffs"]
    assert np.abs(np.diff(smooth[6:18], axis=0)).max() < 0.5 * np.abs(np.diff(raw[6:18], axis=0)).max()
    np.testing.assert_allclose(smooth.sum(axis=2)[:, :6], 1.0, atol=1e-9)
