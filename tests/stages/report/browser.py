"""Open a report page in headless Chromium (Debian's ``chromium`` through ``playwright``).

``python -m tests.stages.report.browser PAGE.html [--screenshot OUT.png]`` prints what the page
did (console errors, requests, images) as JSON and optionally saves a screenshot of its top.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

from editor.browser import chromium

VIEWPORT = {"width": 1200, "height": 1000}


@dataclass
class Visit:
    """What loading a page did: console errors, page errors, every requested URL, and per image
    its ``naturalWidth`` and ``naturalHeight``."""

    console_errors: list[str] = field(default_factory=list)
    page_errors: list[str] = field(default_factory=list)
    requests: list[str] = field(default_factory=list)
    images: list[tuple[int, int]] = field(default_factory=list)


def visit(browser, page_path: Path, *, screenshot: Path | None = None) -> Visit:
    """Load ``page_path`` (file URL) in a new page of the playwright ``browser``, wait until
    loaded, record a :class:`Visit`; optionally save a PNG screenshot of the viewport (the top of
    the page)."""
    seen = Visit()
    page = browser.new_page(viewport=VIEWPORT)
    try:
        page.on("console", lambda m: seen.console_errors.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda e: seen.page_errors.append(str(e)))
        page.on("request", lambda r: seen.requests.append(r.url))
        page.goto(page_path.resolve().as_uri(), wait_until="load")
        seen.images = [
            tuple(size) for size in page.eval_on_selector_all("img", "els => els.map(e => [e.naturalWidth, e.naturalHeight])")
        ]
        if screenshot is not None:
            page.screenshot(path=str(screenshot), type="png")
    finally:
        page.close()
    return seen


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("page", type=Path)
    parser.add_argument("--screenshot", type=Path)
    args = parser.parse_args()
    with chromium() as browser:
        seen = visit(browser, args.page, screenshot=args.screenshot)
    seen.requests = [url[:80] for url in seen.requests]
    print(json.dumps(asdict(seen), indent=1))


if __name__ == "__main__":
    main()
