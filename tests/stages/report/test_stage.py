"""``report.sheet`` and ``write.report`` on synthetic inputs: the page's embedded series against the
ground truth of the inputs, the frames the sheet reads, byte-identical pages across runs and
processes, input errors."""

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from runner.stage import StageError
from stages.layout import load_layout
from stages.report.stage import ContactSheet, WriteReport
from tests.memory_stream import files_context
from tests.stages.report import synthetic

SHEET_PARAMS = {"sheet_frames": 5, "thumb_height": 48}
PARAMS = {"title": "test report"}
SHEET_PORTS = ("performer", "result", "target", "tracked", "pose", "displacements")
REPO = Path(__file__).resolve().parents[3]


def stage_inputs(**options):
    return {k: v for k, v in synthetic.inputs(**options).items() if not k.startswith("truth")}


def sheet(inputs) -> dict:
    """``report.sheet``'s bundle for the stage inputs ``inputs`` (those it reads)."""
    ports = {port: inputs[port] for port in SHEET_PORTS if port in inputs}
    return ContactSheet().run(ports, SHEET_PARAMS, files_context(Path("/nonexistent")))["sheet"]


def write(inputs, root: Path) -> Path:
    """``report.sheet`` then ``write.report`` on ``inputs``, as a pipeline connects them."""
    bundles = {port: value for port, value in inputs.items() if port not in ("performer", "result")}
    WriteReport().run({**bundles, "sheet": sheet(inputs)}, PARAMS, files_context(root))
    return root / "report" / "index.html"


def embedded(page: Path) -> dict:
    match = re.search(r'<script type="application/json" id="report-data">(.*?)</script>', page.read_text(), re.S)
    return json.loads(match.group(1).replace("<\\/", "</"))


def nan(values) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], np.float64)


def test_page_series_match_the_inputs(tmp_path: Path):
    truth = synthetic.inputs()
    data = embedded(write({k: v for k, v in truth.items() if not k.startswith("truth")}, tmp_path))
    face = np.ones(len(truth["truth_target_open"]), bool)
    face[list(synthetic.NO_FACE)] = False
    np.testing.assert_allclose(data["expression"]["mouth_open"]["target"], truth["truth_target_open"], atol=1e-9)
    performer = nan(data["expression"]["mouth_open"]["performer"])
    np.testing.assert_allclose(performer[face], truth["truth_performer_open"][face], atol=1e-9)
    assert np.isnan(performer[~face]).all()
    np.testing.assert_allclose(data["expression"]["mouth_width"]["target"], 0.0, atol=1e-9)
    for k, key in enumerate(("yaw", "pitch", "roll")):
        pose = nan(data["head_pose"][key])
        np.testing.assert_allclose(pose[face], truth["truth_ypr_deg"][face, k], atol=1e-9)
    np.testing.assert_array_equal(data["no_face"], ~face)
    np.testing.assert_array_equal(data["tracking"]["valid_fraction"], face.astype(float))
    np.testing.assert_array_equal(data["limited"], truth["mapped"]["range_limited"])
    np.testing.assert_array_equal(data["propagation"]["iterations"], truth["target"]["iterations"])
    coeff = np.nan_to_num(truth["coefficients"]["coeff"])
    np.testing.assert_array_equal(data["coefficients"]["example"], coeff.argmax(axis=2))
    np.testing.assert_allclose(data["coefficients"]["weight"], coeff.max(axis=2))
    p, t = truth["truth_performer_open"][face], truth["truth_target_open"][face]
    assert data["follow"]["mouth_open"]["r"] == pytest.approx(np.corrcoef(p, t)[0, 1], abs=1e-9)
    assert data["follow"]["mouth_open"]["amplitude_ratio"] == pytest.approx(t.std() / p.std(), abs=1e-9)
    T = len(face)
    sheet = [frame for frame, _ in data["contact_sheet"]]
    peak = int(np.argmax(truth["truth_performer_open"]))
    assert set(np.round(np.linspace(0, T - 1, SHEET_PARAMS["sheet_frames"])).astype(int)) | {peak} == set(sheet)
    assert dict(data["contact_sheet"])[peak] == "mouth open max"
    warnings = "\n".join(data["warnings"])
    assert "No face in 3 of 40 frames: 5-7" in warnings
    assert "soft-limited to the target pack's range in 3 of 40 frames: 10-11, 20" in warnings
    assert "Reference (neutral) frame: 0 (the run records none" in warnings


def test_recorded_neutral_frame_and_tracked_subset(tmp_path: Path):
    """The paper's tracked subset of points still gives performer signals (over the shared lip and
    brow points), and the displacements' ``neutral_frame`` is the reference of every signal."""
    tracked = tuple(load_layout("zhang134").point_names[i] for i in load_layout("zhang134").tracked)
    inputs = stage_inputs(tracked_names=tracked, with_mapped=False)
    T = len(inputs["tracked"]["xy"])
    inputs["displacements"] = {"neutral_frame": np.array(10)}
    data = embedded(write(inputs, tmp_path))
    truth = synthetic.mouth_opening(T, 0.1, T // 2 + 2)
    performer = nan(data["expression"]["mouth_open"]["performer"])
    keep = np.isfinite(performer)
    np.testing.assert_allclose(performer[keep], (truth - truth[10])[keep], atol=1e-9)
    assert data["reference_frame"] == 10 and data["limited"] is None
    assert "Reference (neutral) frame: 10 (recorded by the run)" in data["warnings"]
    assert "Not available: the run records no per-frame range limit" in (tmp_path / "report" / "index.html").read_text()


def test_reads_only_the_contact_sheet_frames_in_ascending_order(tmp_path: Path):
    """One read per chosen frame and stream, in ascending order (so a stream being computed hands
    each frame over as it passes, see runner.broadcast), no whole chunk."""
    inputs = stage_inputs()
    read = []
    for port in ("performer", "result"):
        stream = inputs[port]
        original = stream.read
        stream.read = lambda a, b, original=original, port=port: read.append((port, a, b)) or original(a, b)
    data = embedded(write(inputs, tmp_path))
    frames = [f for f, _ in data["contact_sheet"]]
    for port in ("performer", "result"):
        assert [(a, b) for p, a, b in read if p == port] == [(f, f + 1) for f in frames]  # sorted: frames are
    assert frames == sorted(frames)
    assert inputs["performer"].reads == 0 and inputs["result"].reads == 0  # chunks() never used


@pytest.mark.subprocess
def test_page_is_byte_identical_across_runs_and_processes(tmp_path: Path):
    first = write(stage_inputs(), tmp_path / "a").read_bytes()
    assert write(stage_inputs(), tmp_path / "b").read_bytes() == first
    script = (
        "import sys; from pathlib import Path; from tests.stages.report.test_stage import write, stage_inputs;"
        "write(stage_inputs(), Path(sys.argv[1]))"
    )
    env = {**os.environ, "PYTHONHASHSEED": "12345", "PYTHONPATH": str(REPO)}
    subprocess.run([sys.executable, "-c", script, str(tmp_path / "c")], cwd=REPO, env=env, check=True, timeout=300)
    assert (tmp_path / "c" / "report" / "index.html").read_bytes() == first


def test_inconsistent_inputs_name_the_port(tmp_path: Path):
    inputs = stage_inputs()
    inputs["pose"]["valid"] = inputs["pose"]["valid"][:-1]
    with pytest.raises(StageError, match="input 'pose' field 'valid'"):
        write(inputs, tmp_path)
    inputs = stage_inputs()
    inputs["coefficients"] = {**inputs["coefficients"], "examples": inputs["coefficients"]["examples"][:3]}
    with pytest.raises(StageError, match="write.report: coefficients 'coeff' must be"):
        write(inputs, tmp_path)


def test_warp_only_and_missing_signal_points_are_said(tmp_path: Path):
    inputs = stage_inputs()
    inputs["coefficients"]["coeff"] = np.where(np.isnan(inputs["coefficients"]["coeff"]), np.nan, 0.0)
    names = inputs["tracked"]["names"]
    keep = np.array([not n.startswith("brow") for n in names])
    inputs["tracked"] = {k: (v[:, keep] if k != "names" else v[keep]) for k, v in inputs["tracked"].items()}
    page = write(inputs, tmp_path)
    data = embedded(page)
    assert "expression" not in data
    assert "warp-only" in "\n".join(data["warnings"])
    assert "Not available: expression signals need one of [&#x27;brow_l_0&#x27;" in page.read_text()


def test_enabled_false_writes_nothing(tmp_path: Path):
    WriteReport().run({"sheet": {}}, {**PARAMS, "enabled": False}, files_context(tmp_path))
    assert not (tmp_path / "report" / "index.html").exists()


def test_states_section_curves_and_the_states_beyond_the_pack(tmp_path: Path):
    """The lip-seal curve is the inner-lip gap (the synthetic neutral's 2 px over 60 px of eye
    distance, plus the opening); frames the mapping flagged beyond the pack are listed by state;
    an estimated neutral is said so, its nearest frame the curves' reference and in the sheet."""
    from stages.geometry.states import STATE_NAMES

    truth = synthetic.inputs()
    inputs = {k: v for k, v in truth.items() if not k.startswith("truth")}
    T = len(truth["truth_target_open"])
    beyond = np.zeros((T, len(STATE_NAMES)), bool)
    beyond[[3, 4, 30], STATE_NAMES.index("eye_l_shut")] = True
    inputs["mapped"] = dict(
        inputs["mapped"], state_names=np.array(STATE_NAMES), beyond_pack=beyond, coverage=np.zeros((len(STATE_NAMES), 2))
    )
    inputs["displacements"] = {
        "neutral_frame": np.array(2),
        "neutral_estimated": np.array(True),
        "neutral_nearest_frame": np.array(12),
    }
    data = embedded(write(inputs, tmp_path))
    np.testing.assert_allclose(data["states"]["mouth_open"]["target"], 2.0 / 60.0 + truth["truth_target_open"], atol=1e-9)
    warnings = "\n".join(data["warnings"])
    assert "Beyond what the target pack's examples show: eye l shut in 3 frames" in warnings
    assert "estimated from the clip, region by region; the nearest single frame, 12" in warnings
    assert data["reference_frame"] == 12 and dict(data["contact_sheet"])[12] == "reference"
    assert "3-4, 30" in (tmp_path / "report" / "index.html").read_text()


def test_occluded_regions_are_shown_and_counted(tmp_path: Path):
    inputs = stage_inputs()
    T = len(inputs["tracked"]["xy"])
    occluded = np.zeros((T, 2), bool)
    occluded[3:9, 0] = True  # the mouth in frames 3-8
    occluded[20, 1] = True
    valid = np.ones(T, bool)
    valid[list(synthetic.NO_FACE)] = False
    inputs["occlusion"] = {
        "regions": np.array(["mouth", "eye_l"]),
        "occluded": occluded,
        "score": np.where(occluded, 0.1, 1.0).astype(np.float32),
        "valid": valid,
    }
    page = write(inputs, tmp_path)
    data = embedded(page)
    assert data["occlusion"] == {"mouth": occluded[:, 0].tolist(), "eye_l": occluded[:, 1].tolist()}
    assert "Occluded face regions: mouth in 6 of 40 frames (3-8); eye_l in 1 of 40 frames (20)" in data["warnings"]
    text = page.read_text()
    assert "Frames judged: 37 of 40." in text and 'alt="occluded face regions"' in text


def test_without_occlusion_the_section_says_why(tmp_path: Path):
    text = write(stage_inputs(), tmp_path).read_text()
    assert "Not available: the run detects no occlusion" in text
    assert "occlusion" not in embedded(tmp_path / "report" / "index.html")
