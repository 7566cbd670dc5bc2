"""The editor as a user starts it (``python -m editor.cli``) on the bundled 240x320 target pack,
and Debian's Chromium driven by playwright for the browser tests."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
PACK = REPO / "fixtures" / "packs" / "target"
CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]


@dataclass(frozen=True)
class Editor:
    url: str      # the page, with its token
    base: str     # http://host:port
    token: str
    process: subprocess.Popen


def start_editor(pack: Path, *extra: str, timeout_s: float = 300.0) -> Editor:
    """Start ``python -m editor.cli --pack PACK`` and read the URL it prints."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    process = subprocess.Popen([sys.executable, "-m", "editor.cli", "--pack", str(pack), *extra], cwd=REPO, env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    deadline = time.monotonic() + timeout_s
    line = ""
    while time.monotonic() < deadline:
        line = process.stdout.readline()
        match = re.search(r"(http://[^/\s]+)/\?token=(\S+)", line)
        if match:
            return Editor(match.group(0), match.group(1), match.group(2), process)
        if not line and process.poll() is not None:
            break
    process.kill()
    raise RuntimeError(f"the editor did not start (exit code {process.poll()}, last line {line!r})")


def stop_editor(editor: Editor) -> None:
    editor.process.terminate()
    try:
        editor.process.wait(timeout=10)
    except subprocess.TimeoutExpired:
        editor.process.kill()


@pytest.fixture(scope="session")
def editor_server():
    editor = start_editor(PACK)
    yield editor
    stop_editor(editor)


def browser_or_skip():
    """Chromium via playwright; skip when it is absent, unless under CI, where that fails."""
    if not CHROMIUM.is_file():
        if os.environ.get("CI"):
            pytest.fail(f"{CHROMIUM} is missing under CI: run .ci/install-browser first")
        pytest.skip(f"{CHROMIUM} is missing (run .ci/install-browser); browser tests need Debian's Chromium")
    from playwright.sync_api import sync_playwright

    return sync_playwright, CHROMIUM_ARGS


@pytest.fixture(scope="session")
def browser():
    sync_playwright, args = browser_or_skip()
    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=str(CHROMIUM), args=args, headless=True)
        yield chromium
        chromium.close()
