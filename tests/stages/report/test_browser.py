"""The report page in headless Chromium: loads with no console or page error, requests nothing
outside its folder, and every image decodes (naturalWidth > 0).

Needs Debian's ``chromium`` (the session's ``browser`` fixture, ``tests/conftest.py``: skipped
without it, unless ``CI`` is set: then it fails).
"""

from pathlib import Path

from tests.stages.report.browser import visit
from tests.stages.report.test_stage import SHEET_PARAMS, embedded, stage_inputs, write


def test_page_loads_cleanly_in_chromium(browser, tmp_path: Path):
    page = write(stage_inputs(), tmp_path)
    shot = tmp_path / "top.png"
    seen = visit(browser, page, screenshot=shot)
    assert seen.console_errors == [] and seen.page_errors == []
    folder = page.parent.resolve().as_uri() + "/"
    outside = [url for url in seen.requests if not (url.startswith(folder) or url.startswith("data:"))]
    assert outside == [], outside
    sheet = len(embedded(page)["contact_sheet"])
    assert len(seen.images) == sheet + 4  # the contact sheet, the three timelines and the heatmap
    assert all(width > 0 and height > 0 for width, height in seen.images), seen.images
    assert seen.images[0][1] == SHEET_PARAMS["thumb_height"]
    assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and shot.stat().st_size < 400_000
