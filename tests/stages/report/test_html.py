"""``report_html``'s contact sheet on worker threads: its frame reads run while the plots are
drawn, the page holds the sheet built one frame after the other on the calling thread and does
not depend on the number of threads, and a failing read reaches the stage as a StageError."""

import threading
from pathlib import Path

import pytest

from runner.stage import StageError
from stages.report import sections
from stages.report.html import contact_sheet, report_html
from stages.report.sheet import sheet_image
from tests.stages.report.test_stage import PARAMS, embedded, stage_inputs, write

WAIT_S = 120.0  # a read waits at most this long for a plot to be drawn (generous: a loaded machine)


def test_sheet_reads_run_while_the_plots_are_drawn(tmp_path: Path, monkeypatch):
    """Each contact-sheet read waits until a timeline has been drawn: built before the plots (one
    part after the other on one thread) it would wait in vain and the page would lack the sheet."""
    drawn, readers, waited = threading.Event(), set(), []
    timeline = sections.timeline

    def drawing(*args, **kwargs):
        drawn.set()
        return timeline(*args, **kwargs)

    monkeypatch.setattr(sections, "timeline", drawing)
    inputs = stage_inputs()
    for port in ("performer", "result"):
        stream = inputs[port]

        def read(a, b, original=stream.read):
            readers.add(threading.current_thread())
            waited.append(drawn.wait(WAIT_S))
            return original(a, b)

        stream.read = read
    page = write(inputs, tmp_path)
    assert waited and all(waited)
    assert threading.current_thread() not in readers
    assert len(embedded(page)["contact_sheet"]) * 2 == len(waited)


def test_page_holds_the_sheet_built_on_the_calling_thread(tmp_path: Path):
    text = write(stage_inputs(), tmp_path).read_text()
    frames = [tuple(entry) for entry in embedded(tmp_path / "report" / "index.html")["contact_sheet"]]
    fresh = stage_inputs()
    jpegs = [sheet_image(fresh["performer"], fresh["result"], f, height=PARAMS["thumb_height"]) for f, _ in frames]
    serial = contact_sheet(frames, jpegs, fps=fresh["performer"].info.fps)
    assert serial.startswith('<div class="sheet"><figure>') and serial in text


def test_page_does_not_depend_on_the_sheet_threads():
    options = {"evenly": 12, "thumb_height": PARAMS["thumb_height"], "title": "threads"}
    one = report_html(stage_inputs(), **options, sheet_threads=1)
    assert report_html(stage_inputs(), **options, sheet_threads=5) == one
    with pytest.raises(ValueError, match="sheet_threads must be >= 1, got 0"):
        report_html(stage_inputs(), **options, sheet_threads=0)


def test_a_failing_frame_read_is_a_stage_error(tmp_path: Path):
    inputs = stage_inputs()

    def broken(a, b):
        raise ValueError(f"frame {a} cannot be decoded")

    inputs["result"].read = broken
    with pytest.raises(StageError, match=r"write.report: frame 0 cannot be decoded"):
        write(inputs, tmp_path)
    assert not (tmp_path / "report" / "index.html").exists()
