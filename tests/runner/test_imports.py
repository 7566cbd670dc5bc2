"""The runner's modules import each other without a cycle, and none imports the command line.

The graph is read from the source (every ``import`` and ``from ... import``, at module level or
inside a function; those under ``if TYPE_CHECKING:`` are annotations only and left out), so a
function-level import that closes a cycle counts as much as a top-level one.
"""

from __future__ import annotations

import ast
from graphlib import CycleError, TopologicalSorter
from pathlib import Path

import pytest

RUNNER = Path(__file__).resolve().parents[2] / "runner"


def _type_checking_only(tree: ast.Module) -> set[ast.AST]:
    """The import nodes under ``if TYPE_CHECKING:`` blocks."""
    skipped: set[ast.AST] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and ast.unparse(node.test) in ("TYPE_CHECKING", "typing.TYPE_CHECKING"):
            for child in node.body:
                skipped.update(ast.walk(child))
    return skipped


def imports_of(source: str, modules: set[str]) -> set[str]:
    """The modules of ``modules`` (dotted names) that ``source`` imports at run time."""
    tree = ast.parse(source)
    skipped = _type_checking_only(tree)
    found: set[str] = set()
    for node in ast.walk(tree):
        if node in skipped:
            continue
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names)  # `from runner import notes`
    return found & modules


def runner_graph() -> dict[str, set[str]]:
    """Each module of the ``runner`` package -> the runner modules it imports (itself excluded)."""
    files = {("runner" if p.stem == "__init__" else f"runner.{p.stem}"): p for p in RUNNER.glob("*.py")}
    return {name: imports_of(path.read_text(encoding="utf-8"), set(files)) - {name} for name, path in files.items()}


def test_the_graph_reader_sees_function_level_imports_and_skips_type_checking_ones():
    source = (
        "from typing import TYPE_CHECKING\n"
        "from runner import notes\n"
        "if TYPE_CHECKING:\n"
        "    from runner.config import Pipeline\n"
        "def f():\n"
        "    from runner.cli import main\n"
        "    import runner.cache\n"
    )
    modules = {"runner", "runner.notes", "runner.config", "runner.cli", "runner.cache"}
    assert imports_of(source, modules) == {"runner", "runner.notes", "runner.cli", "runner.cache"}


def test_a_cycle_is_detected():
    with pytest.raises(CycleError):
        tuple(TopologicalSorter({"runner.a": {"runner.b"}, "runner.b": {"runner.a"}}).static_order())


def test_the_runner_imports_no_cycle():
    graph = runner_graph()
    assert {"runner.cli", "runner.execute", "runner.offload", "runner.signals"} <= set(graph)
    tuple(TopologicalSorter(graph).static_order())  # raises CycleError naming the cycle


def test_no_runner_module_imports_the_command_line():
    assert [name for name, deps in runner_graph().items() if "runner.cli" in deps] == []
