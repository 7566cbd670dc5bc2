"""Shared test setup: the repository root on sys.path (for `scripts.*`), torch kept to 2 threads,
and one headless Chromium per test session for the browser tests (editor, run report)."""

import os
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))


@pytest.fixture(scope="session")
def browser():
    """Debian's Chromium via playwright, one per session (playwright's sync API allows one
    instance per thread); skipped when it is absent, unless under CI, where that fails."""
    from editor.browser import CHROMIUM, chromium

    if not CHROMIUM.is_file():
        if os.environ.get("CI"):
            pytest.fail(f"{CHROMIUM} is missing under CI: run .ci/install-browser first")
        pytest.skip(f"{CHROMIUM} is missing (run .ci/install-browser); the browser tests need Debian's Chromium")
    with chromium() as instance:
        yield instance
