"""The markers `make test-fast` selects by (tests/conftest.py): a test that starts a Python
process without its marker fails; ``browser`` follows the use of the browser fixture."""

from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

CONFTEST = (Path(__file__).parent / "conftest.py").read_text()
MARKERS = "[pytest]\nmarkers =\n    slow: s\n    subprocess: s\n    browser: s\n    ray: s\naddopts = --strict-markers\n"


@pytest.mark.subprocess  # its marked inner test starts one
def test_a_test_that_starts_python_needs_the_subprocess_marker(pytester: pytest.Pytester) -> None:
    pytester.makeconftest(CONFTEST)
    pytester.makeini(MARKERS)
    pytester.makepyfile(
        """
        import subprocess, sys
        import pytest

        def test_unmarked():
            subprocess.run([sys.executable, "-c", "pass"], check=True)

        @pytest.mark.subprocess
        def test_marked():
            subprocess.run([sys.executable, "-c", "pass"], check=True)

        def test_another_program():
            subprocess.run(["true"], check=True)
        """
    )
    result = pytester.runpytest_inprocess("-q", "-p", "no:cacheprovider")
    result.assert_outcomes(passed=2, failed=1)
    result.stdout.fnmatch_lines(["*test_unmarked starts a Python process*mark it subprocess*"])


def test_the_browser_fixture_gives_the_browser_marker(pytester: pytest.Pytester) -> None:
    pytester.makeconftest(
        CONFTEST.replace(
            '@pytest.fixture(scope="session")\ndef browser():', '@pytest.fixture(scope="session")\ndef _real_browser():'
        )
    )
    pytester.makeini(MARKERS)
    pytester.makepyfile(
        """
        import pytest

        @pytest.fixture
        def browser():
            return None

        @pytest.fixture
        def page(browser):
            return browser

        def test_through_another_fixture(page):
            pass

        def test_without():
            pass
        """
    )
    result = pytester.runpytest_inprocess("-q", "-p", "no:cacheprovider", "-m", "browser")
    result.assert_outcomes(passed=1, deselected=1)
