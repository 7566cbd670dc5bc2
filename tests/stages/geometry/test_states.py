"""Expression states of a geometry (stages.geometry.states) against hand-made faces."""

from __future__ import annotations

import numpy as np
import pytest

from stages.geometry.states import STATE_NAMES, STATES, beyond_coverage, coverage, state_signals, state_values
from stages.layout import load_layout
from tests.stages.geometry.test_mapping import eyed_face


def test_signals_of_a_hand_made_face_are_its_measures():
    """Outer eye corners 150 px apart; lids 12 px apart; outer lips an ellipse 60 x 16 px with the
    inner lips touching at its middle; brows placed 40 px above the eye line, inner ends 50 px apart;
    turned by 30 deg and scaled by 2: every signal is the same in eye distances."""
    layout = load_layout("zhang134")
    xy = eyed_face(layout, eye_gap=12.0)
    names = layout.point_names
    s = state_signals(xy, names)
    assert s["eye_distance_px"] == pytest.approx(150.0)
    assert s["eye_open_l"] == pytest.approx(12.0 / 150.0) and s["eye_open_r"] == pytest.approx(12.0 / 150.0)
    assert s["mouth_open"] == pytest.approx(0.0, abs=1e-12)
    assert s["mouth_width"] == pytest.approx(60.0 / 150.0)
    assert s["lip_thickness"] == pytest.approx(16.0 / 150.0)
    assert s["smile"] == pytest.approx(0.0, abs=1e-12)  # corners level with the lips' middle
    assert s["brow_raise"] == pytest.approx(40.0 / 150.0)
    assert s["brow_furrow"] == pytest.approx(50.0 / 150.0)
    angle = np.radians(30.0)
    turn = 2.0 * np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    turned = state_signals(xy @ turn.T + 7.0, names)
    for key in s:
        expected = s[key] * (2.0 if key == "eye_distance_px" else 1.0)
        assert turned[key] == pytest.approx(expected, abs=1e-12), key


def test_states_are_read_against_the_neutral_and_a_pack_range():
    """A neutral, a frame with the left eye shut, one with the mouth wide open and the brows
    together: each state is present where it should be; a pack spanning only the neutral and the
    open mouth covers the jaw but not the shut eye or the furrow."""
    layout = load_layout("zhang134")
    names = layout.point_names
    neutral = eyed_face(layout, eye_gap=12.0)
    shut = neutral.copy()
    for k in range(1, 6):
        shut[layout.index(f"eye_l_{k}"), 1] += 12.0
    wide = neutral.copy()
    for k in range(6, 10):
        wide[layout.index(f"mouth_inner_{k}"), 1] += 40.0
    for side, toward in (("l", 12.0), ("r", -12.0)):
        for k in (0, 7):
            wide[layout.index(f"brow_{side}_{k}"), 0] += toward
    values = state_values(np.stack([neutral, shut, wide]), names, neutral)
    present = {s.name: s.present(values[s.name]) for s in STATES}
    np.testing.assert_array_equal(present["eye_l_shut"], [False, True, False])
    np.testing.assert_array_equal(present["eye_r_shut"], [False, False, False])
    np.testing.assert_array_equal(present["lips_sealed"], [True, True, False])
    np.testing.assert_array_equal(present["jaw_open"], [False, False, True])
    np.testing.assert_array_equal(present["brow_furrow"], [False, False, True])
    covered = coverage(wide[None], names, neutral)
    assert set(covered) == set(STATE_NAMES)
    beyond = beyond_coverage(values, covered)
    np.testing.assert_array_equal(beyond["eye_l_shut"], [False, True, False])
    assert not beyond["jaw_open"].any() and not beyond["brow_furrow"].any()
    np.testing.assert_array_equal(
        beyond_coverage(values, covered, np.array([True, False, True]))["eye_l_shut"], [False, False, False]
    )
