"""Shared test setup: the repository root on sys.path (for `scripts.*`), torch kept to 2 threads,
one headless Chromium per test session for the browser tests (editor, run report), and the
markers `make test-fast` selects by (pyproject.toml): ``browser`` given here to every test that
uses the browser, and a test that starts a Python process without its ``subprocess`` (or
``ray``, ``browser``) marker fails, so that the fast subset holds no such test."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

PROCESS_MARKERS = ("subprocess", "ray", "browser")

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


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if "browser" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.browser)


def _is_python(args: object) -> bool:
    """Whether ``subprocess.Popen(args)`` starts Python: this interpreter, a ``python*``
    executable, or one of the package's console scripts (which are Python programs)."""
    program = args[0] if isinstance(args, (list, tuple)) and args else args
    name = Path(os.fsdecode(program)).name if isinstance(program, (str, bytes, os.PathLike)) else ""
    return str(program) == sys.executable or name.startswith("python") or name in ("runner", "expression-editor", "ray")


@pytest.fixture(autouse=True)
def _python_processes_are_marked(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    """Fail a test that starts a Python process unless it is marked for it."""
    if any(request.node.get_closest_marker(name) for name in PROCESS_MARKERS):
        return
    started = subprocess.Popen.__init__

    def checked(self: subprocess.Popen, args: object, *rest: object, **options: object) -> None:
        if _is_python(args):
            pytest.fail(f"{request.node.nodeid} starts a Python process ({args!r}): mark it subprocess", pytrace=False)
        started(self, args, *rest, **options)

    monkeypatch.setattr(subprocess.Popen, "__init__", checked)
