"""The synthetic occluder of ``scripts/occluder.py``: the hand drawn, pasted where it should be,
the coverage truth against shapes of known area, the benchmark's schedule and rows."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from scripts import occluder
from stages.layout import load_layout
from stages.occlusion.regions import REGIONS

REPO = Path(__file__).resolve().parents[2]
CLIP = REPO / "fixtures" / "realface" / "astro.mp4"
NAMES = list(load_layout("zhang134").point_names)


def square_face(side: float = 40.0) -> np.ndarray:
    """Layout points ``(N, 2)``: every region's outline a square of ``side`` px (mouth at
    (100, 200), others elsewhere), outer eye corners 100 px apart."""
    layout = load_layout("zhang134")
    xy = np.zeros((len(NAMES), 2))
    centres = {
        "mouth": (100, 200),
        "eye_l": (60, 100),
        "eye_r": (140, 100),
        "brow_l": (60, 60),
        "brow_r": (140, 60),
        "nose": (100, 150),
    }
    for region, outline in occluder.REGION_OUTLINES.items():
        polygon = layout.subregion(outline).polygon
        corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * side / 2 + centres[region]
        for k, i in enumerate(polygon):  # the outline's points spread over the square's corners
            xy[i] = corners[min(4 * k // len(polygon), 3)]
    xy[NAMES.index("eye_l_6")], xy[NAMES.index("eye_r_6")] = (50, 100), (150, 100)
    return xy


def test_coverage_is_the_hidden_fraction_of_each_outline():
    xy = square_face()
    alpha = np.zeros((300, 300), np.float32)
    alpha[:, :100] = 1.0  # the left half of the mouth and nose squares, all of eye_l and brow_l
    fraction = dict(zip(REGIONS, occluder.coverage(alpha, xy, NAMES)))
    assert fraction["mouth"] == pytest.approx(0.5, abs=0.05) and fraction["nose"] == pytest.approx(0.5, abs=0.05)
    assert fraction["eye_l"] == 1.0 and fraction["brow_l"] == 1.0
    assert fraction["eye_r"] == 0.0 and fraction["brow_r"] == 0.0
    assert np.isnan(occluder.coverage(alpha, xy + 1000, NAMES)).all()  # outside the frame


def test_a_collapsed_outline_is_still_measured():
    xy = square_face()
    eye = [NAMES.index(f"eye_l_{k}") for k in range(12)]
    xy[eye, 1] = 100.0  # a shut eye: the outline is a line
    alpha = np.zeros((300, 300), np.float32)
    alpha[90:110, :] = 1.0
    assert occluder.coverage(alpha, xy, NAMES)[REGIONS.index("eye_l")] == 1.0


def test_hand_is_opaque_inside_soft_at_its_edge_and_shaded():
    hand = occluder.make_hand()
    assert hand.alpha.min() >= 0.0 and hand.alpha.max() <= 1.0
    inside = hand.alpha > 0.99
    palm_area = np.pi * 0.5 * 0.58 * hand.palm_px**2
    assert 1.5 * palm_area < inside.sum() < 3.0 * palm_area  # palm and five digits
    edge = (hand.alpha > 0.05) & (hand.alpha < 0.95)
    assert 0 < edge.sum() < 0.2 * inside.sum()
    shade = hand.shade[inside]
    assert shade.min() > 0.1 and shade.std() > 0.05  # lit, not flat


def test_pasting_leaves_the_frame_alone_away_from_the_hand_and_its_shadow():
    frame = np.random.default_rng(0).integers(0, 256, (240, 320, 3), np.uint8)
    hand = occluder.make_hand()
    transform = occluder.hand_transform(hand, np.array([100.0, 120.0]), 60.0, 90.0)
    out, alpha = occluder.paste_hand(frame, hand, transform, np.array([200.0, 150.0, 120.0]))
    assert alpha.shape == (240, 320) and alpha[120, 100] > 0.99  # the palm's centre
    far = np.zeros((240, 320), bool)
    far[:, 230:] = True  # beyond the fingertips (60 px palm: fingers reach about 110 px) and the shadow
    assert np.abs(out[far].astype(int) - frame[far]).max() <= 1
    palm = out[110:130, 90:110].reshape(-1, 3).mean(axis=0)
    assert (np.abs(palm - [200, 150, 120]) < 60).all() and palm[0] > palm[1] > palm[2]  # skin, shaded


def test_events_schedule_the_mouth_first_then_an_eye_in_the_middle():
    xy = np.tile(square_face(), (100, 1, 1))
    events = occluder.default_events(xy, NAMES, np.ones(100, bool), np.array([200.0, 150.0, 120.0]), frames=30)
    assert [(e.region, e.start, e.stop) for e in events][0] == ("mouth", 0, 30)
    assert events[1].region in ("eye_l", "eye_r") and (events[1].start, events[1].stop) == (35, 65)
    assert events[0].colour == (200.0, 150.0, 120.0) and events[1].colour != events[0].colour
    with pytest.raises(ValueError, match="too short"):
        occluder.default_events(xy[:60], NAMES, np.ones(60, bool), np.array([200.0, 150.0, 120.0]), frames=30)


def test_recall_precision_count_frames_and_regions():
    truth = np.zeros((4, 2), bool)
    truth[:2, 0] = True
    flagged = np.zeros((4, 2), bool)
    flagged[1:3, 0] = True
    assert occluder.recall_precision(flagged, truth) == (0.5, 0.5)
    recall, precision = occluder.recall_precision(np.zeros((4, 2), bool), truth)
    assert recall == 0.0 and np.isnan(precision)


@pytest.mark.slow
def test_rows_of_the_real_texture_clip(tmp_path):
    """The benchmark's rows on the 48-frame real-texture clip with 12-frame events (a dev clip
    takes the 30-frame default)."""
    rows = occluder.occlusion_rows(CLIP, tmp_path, event_frames=12)
    value = {r["metric"]: r["value"] for r in rows}
    assert value["real_occlusion_false_frac_astro"] == 0.0
    assert value["real_occlusion_recall_astro"] >= 0.9 and value["real_occlusion_precision_astro"] >= 0.8
    assert value["real_occlusion_recall_mouth_astro"] >= 0.9
    assert {f"real_occlusion_false_frac_{r}_astro" for r in REGIONS} <= set(value)
    assert value["real_occlusion_half_recall_astro"] >= 0.9 and value["real_occlusion_half_precision_astro"] >= 0.8
    truth = np.load(tmp_path / "occluded_truth.npz", allow_pickle=False)
    assert truth["covered"].shape == (48, len(REGIONS)) and truth["covered"][:12, REGIONS.index("mouth")].all()
    half = np.load(tmp_path / "half_truth.npz", allow_pickle=False)["covered"]
    assert half[:24, REGIONS.index("mouth")].all() and not half[24:, REGIONS.index("mouth")].any()
    assert (tmp_path / "occluded.mp4").stat().st_size > 0 and (tmp_path / "half.mp4").stat().st_size > 0
    assert all(set(r) == {"bench", "metric", "value", "unit"} and r["bench"] == "real" for r in rows)
    json.dumps(rows)


@pytest.mark.subprocess
def test_cli_says_in_one_line_when_a_clip_is_too_short(tmp_path):
    result = subprocess.run(
        [sys.executable, "scripts/occluder.py", "--clip", str(CLIP), "--work", str(tmp_path)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 1 and "Traceback" not in result.stderr
    said = [line for line in result.stderr.splitlines() if line.startswith("occluder:")]
    assert said == [f"occluder: {CLIP}: clip too short for 30-frame occluder events: 48 frames, need 70"]


def test_aggregates_are_over_the_clips_and_the_variants_there():
    rows = [
        occluder.row(f"real_occlusion_{k}_{s}", v, "fraction")
        for s, values in (("a", (0.9, 0.8, 0.0)), ("b", (1.0, np.nan, 0.01)))
        for k, v in zip(("recall", "precision", "false_frac"), values)
    ]
    value = {r["metric"]: r["value"] for r in occluder.aggregate_rows(rows, ["a", "b"])}
    assert value == {"real_occlusion_recall_min": 0.9, "real_occlusion_precision_min": 0.8, "real_occlusion_false_frac_max": 0.01}
