"""Expression signals: known lip and brow displacements, invariance to roll and scale."""

import numpy as np
import pytest

from stages.actor_pack import load_pack
from stages.geometry.signals import LOWER_INNER_LIP, BROWS, expression_signals, follow

PACK = "fixtures/packs/target"


def test_signals_measure_known_displacements_under_roll_and_scale():
    pack = load_pack(PACK)
    names = pack.layout.point_names
    neutral = pack.neutral.points
    eye = np.linalg.norm(neutral[names.index("eye_r_6")] - neutral[names.index("eye_l_6")])
    moved = neutral.copy()
    moved[[names.index(n) for n in LOWER_INNER_LIP], 1] += 0.2 * eye
    moved[[names.index(n) for n in BROWS], 1] -= 0.05 * eye
    base = expression_signals(neutral[None], names)
    after = expression_signals(moved[None], names)
    assert after["mouth_open"][0] - base["mouth_open"][0] == pytest.approx(0.2, abs=0.02)  # eye line ~level
    assert after["brow_raise"][0] - base["brow_raise"][0] == pytest.approx(0.05, abs=0.005)
    angle = np.radians(25)
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    turned = expression_signals((1.7 * moved @ rot.T + [30, -12])[None], names)
    for key in ("mouth_open", "mouth_width", "brow_raise"):
        assert turned[key][0] == pytest.approx(after[key][0], abs=1e-9)


def test_follow_correlation_and_amplitude():
    t = np.linspace(0, 6, 200)
    performer = np.sin(t)
    r, ratio = follow(performer, 0.5 * performer + 3)
    assert r == pytest.approx(1.0) and ratio == pytest.approx(0.5)
    r, _ = follow(performer, -performer)
    assert r == pytest.approx(-1.0)
    assert np.isnan(follow(np.ones(10), performer[:10])[0])
