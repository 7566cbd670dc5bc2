"""The command line of a generated documentation page: write it, or with ``--check`` exit 1 when
the page on disk is not what its sources give (``scripts/benchmarks_page.py``,
``scripts/stages_page.py``)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path


def page_main(path: Path, render: Callable[[], str], *, name: str, script: str, sources: str, argv: list[str] | None) -> int:
    """Write ``render()`` to ``path`` (shown as ``name``); with ``--check``, exit 1 when ``path``
    differs from it, naming ``script`` to run; ``sources``: what the page is rendered from."""
    parser = argparse.ArgumentParser(description=f"Render {name} from the {sources}.")
    parser.add_argument("--check", action="store_true", help=f"exit 1 when {name} is not what the {sources} give")
    args = parser.parse_args(argv)
    text = render()
    if args.check:
        if not path.is_file() or path.read_text(encoding="utf-8") != text:
            print(f"{name} is not up to date: run python {script}", file=sys.stderr)
            return 1
        return 0
    path.write_text(text, encoding="utf-8")
    return 0
