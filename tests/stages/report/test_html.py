"""The contact sheet between ``report.sheet`` and ``write.report``: the page shows the sheet
bundle's JPEGs, which are the performer | result images of the chosen frames; a bundle whose
fields disagree, and a failing frame read, are stage errors naming the stage."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from runner.stage import StageError
from stages.report.html import contact_sheet
from stages.report.sheet import sheet_images
from stages.report.stage import WriteReport
from stages.writers.preview import side_by_side
from tests.memory_stream import files_context
from tests.stages.report.test_stage import PARAMS, SHEET_PARAMS, embedded, sheet, stage_inputs, write


def test_page_shows_the_sheet_images(tmp_path: Path):
    inputs = stage_inputs()
    text = write(inputs, tmp_path).read_text()
    images = sheet_images(sheet(inputs))
    assert [[f, label] for f, label, _ in images] == embedded(tmp_path / "report" / "index.html")["contact_sheet"]
    html = contact_sheet(images, fps=inputs["performer"].info.fps)
    assert html.startswith('<div class="sheet"><figure>') and html in text


def test_sheet_images_are_the_chosen_frames_side_by_side():
    """Each JPEG decodes to performer | result of its own frame at the thumbnail height: closer to
    it than to any other chosen frame's, and within JPEG's loss (OpenCV's decoder, the frames)."""
    inputs = stage_inputs()
    images = sheet_images(sheet(inputs))
    expected = {
        frame: side_by_side(
            inputs["performer"].frames[frame], inputs["result"].frames[frame], height=SHEET_PARAMS["thumb_height"]
        )
        for frame, _, _ in images
    }
    for frame, _, jpeg in images:
        decoded = cv2.cvtColor(cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        error = {f: np.abs(decoded.astype(int) - pair).mean() for f, pair in expected.items()}
        assert error[frame] < 8.0 and error[frame] == min(error.values()), (frame, error)


def test_inconsistent_sheet_bundle_is_a_stage_error(tmp_path: Path):
    inputs = stage_inputs()
    bundles = {port: value for port, value in inputs.items() if port not in ("performer", "result")}
    bad = {**sheet(inputs)}
    bad["jpeg_end"] = bad["jpeg_end"][:-1]
    with pytest.raises(StageError, match=r"write.report: sheet: \d+ frames, \d+ labels and \d+ JPEG ends"):
        WriteReport().run({**bundles, "sheet": bad}, PARAMS, files_context(tmp_path))
    assert not (tmp_path / "report" / "index.html").exists()


def test_a_failing_frame_read_is_a_stage_error(tmp_path: Path):
    inputs = stage_inputs()

    def broken(a, b):
        raise ValueError(f"frame {a} cannot be decoded")

    inputs["result"].read = broken
    with pytest.raises(StageError, match=r"report.sheet: frame 0 cannot be decoded"):
        write(inputs, tmp_path)
    assert not (tmp_path / "report" / "index.html").exists()
