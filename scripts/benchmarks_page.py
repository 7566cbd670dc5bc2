"""Render ``docs/benchmarks.md`` from the benchmark records (``benchmarks/results/*.jsonl``).

    python scripts/benchmarks_page.py [--check]

For each area, the latest record of each metric: its value and unit, the commit and date of the
run that recorded it, and the machine's load then. A row is marked *stale* when a file its area
depends on (:data:`DEPENDS`, paths relative to the repository) changed after the recorded commit,
or when it was recorded from a checkout with uncommitted changes; a Python or YAML file
whose change is only comments, docstrings or layout does not count. ``--check`` exits 1 when the
page on disk differs from what the records give.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))  # scripts.generated_page when run as a script

from scripts.generated_page import page_main  # noqa: E402

RESULTS = REPO / "benchmarks" / "results"
PAGE = REPO / "docs" / "benchmarks.md"
CODE = ("runner", "stages", "lab", "pipeline.yaml", "pack_build.yaml")  # what every area's figures depend on
DEPENDS = {
    "real": CODE + ("scripts/bench_real.py", "scripts/real_states.py", "scripts/occluder.py"),
    "shot": CODE + ("scripts/bench_shot.py", "pipeline_3d.yaml"),
    "seen": CODE + ("scripts/bench_seen.py", "scripts/bench_real.py", "scripts/real_states.py"),
    "e2e": CODE + ("scripts/bench_e2e.py", "scripts/make_fixtures.py"),
}


def latest(path: Path) -> dict[str, dict]:
    """The last record of each metric of one area's file, in first-recorded order."""
    rows: dict[str, dict] = {}
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.strip():
            entry = json.loads(line)
            rows.pop(entry["metric"], None)
            rows[entry["metric"]] = entry
    return rows


def code_of(source: str) -> str:
    """What a Python file does: its syntax tree without docstrings, type annotations and the
    imports for the type checker alone (``if TYPE_CHECKING:``, ``from typing import
    TYPE_CHECKING``); comments and layout are not in it. Annotations are for the type checker
    (the code postpones their evaluation, ``from __future__ import annotations``); an annotated
    assignment keeps its place, so that a dataclass field stays a field."""
    tree = ast.parse(source)
    for node in ast.walk(tree):
        if isinstance(node, ast.arg):
            node.annotation = None
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            node.returns = None
        elif isinstance(node, ast.AnnAssign):
            node.annotation = ast.Constant(value=None)
        for field in ("body", "orelse"):
            statements = getattr(node, field, None)
            if isinstance(statements, list):
                setattr(node, field, [s for s in statements if not _type_checking_block(s)])
        body = getattr(node, "body", None)
        if (
            isinstance(body, list)
            and body
            and isinstance(body[0], ast.Expr)
            and isinstance(body[0].value, ast.Constant)
            and isinstance(body[0].value.value, str)
        ):
            node.body = body[1:] or [ast.Pass()]
    return ast.dump(tree)


def _type_checking_block(node: ast.AST) -> bool:
    """``if TYPE_CHECKING:`` with no ``else``, or ``from typing import TYPE_CHECKING``."""
    if isinstance(node, ast.ImportFrom):
        return node.module == "typing" and [alias.name for alias in node.names] == ["TYPE_CHECKING"]
    return isinstance(node, ast.If) and not node.orelse and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING"


def git(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True)


def changed_since(commit: str, paths: tuple[str, ...]) -> bool:
    """Whether a file under ``paths`` does something else at HEAD than at ``commit`` (True when
    unknown): a Python file whose code is the same (:func:`code_of`: only comments, docstrings or
    layout changed) or a YAML file with the same content (only comments changed) does not count;
    any other file counts by its bytes."""
    if commit.endswith("-dirty") or commit == "unknown":
        return True
    names = git("diff", "--name-only", commit, "HEAD", "--", *paths)
    if names.returncode != 0:
        return True
    for name in names.stdout.split():
        before, after = git("show", f"{commit}:{name}"), git("show", f"HEAD:{name}")
        if before.returncode != 0 or after.returncode != 0 or not name.endswith((".py", ".yaml")):
            return True
        meaning = code_of if name.endswith(".py") else yaml.safe_load
        try:
            if meaning(before.stdout) != meaning(after.stdout):
                return True
        except (SyntaxError, yaml.YAMLError):
            return True
    return False


def page() -> str:
    lines = [
        "# Benchmark figures",
        "",
        "Generated by `python scripts/benchmarks_page.py` from `benchmarks/results/*.jsonl` (appended by",
        "`python scripts/bench.py AREA --json --record`): the latest record of each metric. *stale*: the code",
        "the area depends on changed after the recorded commit (or the run had uncommitted changes); record",
        "the area again.",
        "",
    ]
    for path in sorted(RESULTS.glob("*.jsonl")):
        area = path.stem
        rows = latest(path)
        stale = {
            c: changed_since(c, DEPENDS.get(area, CODE + (f"scripts/bench_{area}.py",)))
            for c in {r["commit"] for r in rows.values()}
        }
        lines += [
            f"## {area}",
            "",
            "| metric | value | unit | commit | date | load (start, end) | |",
            "|---|---|---|---|---|---|---|",
        ]
        for metric, r in rows.items():
            value = r["value"]
            shown = f"{value:.4g}" if isinstance(value, float) else str(value)
            load = f"{r['machine']['load_start']}, {r['machine']['load_end']}"
            lines.append(
                f"| `{metric}` | {shown} | {r['unit']} | {r['commit'][:10]} | {r['date'][:10]} | {load} "
                f"| {'stale' if stale[r['commit']] else ''} |"
            )
        lines.append("")
    return "\n".join(lines)


def missing_commits() -> list[str]:
    """The recorded commits this clone does not hold (a shallow clone): staleness cannot be told."""
    commits = {r["commit"] for path in RESULTS.glob("*.jsonl") for r in latest(path).values()}
    return sorted(
        c for c in commits if c != "unknown" and git("cat-file", "-e", f"{c.removesuffix('-dirty')}^{{commit}}").returncode
    )


def main(argv: list[str] | None = None) -> int:
    checking = "--check" in (sys.argv[1:] if argv is None else argv)
    if checking and (missing := missing_commits()):
        print(
            f"docs/benchmarks.md not checked: this clone lacks {len(missing)} recorded commits (git fetch --unshallow)",
            file=sys.stderr,
        )
        return 0
    return page_main(
        PAGE, page, name="docs/benchmarks.md", script="scripts/benchmarks_page.py", sources="benchmark records", argv=argv
    )


if __name__ == "__main__":
    raise SystemExit(main())
