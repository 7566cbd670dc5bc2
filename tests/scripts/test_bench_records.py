"""Benchmark records (scripts/bench.py --record) and the page rendered from them
(scripts/benchmarks_page.py): provenance kept, the latest record shown, stale rows marked."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

from scripts import bench, benchmarks_page


def git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", *args], cwd=repo, capture_output=True, text=True, check=True).stdout.strip()


def test_records_keep_provenance_and_the_page_shows_the_latest_marking_stale_ones(tmp_path, monkeypatch):
    repo = tmp_path / "repo"
    (repo / "stages").mkdir(parents=True)
    (repo / "stages" / "a.py").write_text("x = 1\n")
    (repo / "pipeline.yaml").write_text("stages:\n  a: 1\n")
    git(repo, "init", "-q")
    git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qam", "one", "--allow-empty")
    git(repo, "add", ".")
    git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "two")
    for module in (bench, benchmarks_page):
        monkeypatch.setattr(module, "REPO", repo)
    monkeypatch.setattr(benchmarks_page, "RESULTS", repo / "benchmarks" / "results")
    monkeypatch.setattr(benchmarks_page, "PAGE", repo / "docs" / "benchmarks.md")
    first = git(repo, "rev-parse", "HEAD")
    started = {"date": "2026-01-01T00:00:00+00:00", "load_start": 0.5, "commit": bench.commit()}
    rows = [
        {"bench": "geometry", "metric": "m_a", "value": 1.0, "unit": "px"},
        {"bench": "geometry", "metric": "m_b", "value": 2.0, "unit": "px"},
    ]
    path = bench.record("geometry", rows, started, ["geometry", "--json", "--record"])
    entries = [json.loads(line) for line in path.read_text().splitlines()]
    assert [e["commit"] for e in entries] == [first, first] and entries[0]["machine"]["cores"] >= 1
    assert entries[0]["command"] == "scripts/bench.py geometry --json --record"
    (repo / "docs").mkdir()
    text = benchmarks_page.page()
    assert "| `m_a` | 1 | px |" in text and "| stale |" not in text
    git(repo, "add", "benchmarks")
    git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "records")
    bench.record("geometry", rows, started, ["geometry"])  # the records themselves changed: not a dirty checkout
    assert bench.commit() == git(repo, "rev-parse", "HEAD")
    (repo / "stages" / "a.py").write_text("x = 9\n")
    assert bench.commit().endswith("-dirty")
    git(repo, "checkout", "-q", "--", "stages")
    (repo / "stages" / "a.py").write_text('"""A module."""\n\nx = (\n    1  # one\n)\n')  # words and layout only
    (repo / "pipeline.yaml").write_text("stages:  # the graph\n  a: 1\n")
    git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qam", "words")
    assert "| stale |" not in benchmarks_page.page()
    bench.record("geometry", [{**rows[0], "value": 3.0}], started, ["geometry"])
    (repo / "stages" / "a.py").write_text("x = 2\n")  # the code the figures depend on changes
    git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qam", "three")
    text = benchmarks_page.page()
    assert "| `m_a` | 3 | px |" in text and "| `m_a` | 1 |" not in text  # the latest record only
    assert text.count("| stale |") == 2  # both rows are stale now
    assert benchmarks_page.main(["--check"]) == 1
    assert benchmarks_page.main([]) == 0 and benchmarks_page.main(["--check"]) == 0


def test_type_annotations_and_type_checking_imports_are_not_code():
    """Annotations and the imports for the type checker alone leave a file's code as it is; a
    changed default, a dropped field or a real import does not."""
    plain = "import os\n\n\ndef f(a, b=1):\n    return a\n\n\nclass C:\n    x = 2\n    y: int\n"
    typed = (
        "import os\nfrom typing import TYPE_CHECKING\n\nif TYPE_CHECKING:\n    import torch\n\n\n"
        "def f(a: torch.Tensor, b: int = 1) -> torch.Tensor:\n    return a\n\n\nclass C:\n    x: int = 2\n    y: str\n"
    )
    assert benchmarks_page.code_of(typed) == benchmarks_page.code_of(plain.replace("    x = 2", "    x: float = 2"))
    assert benchmarks_page.code_of(plain) != benchmarks_page.code_of(plain.replace("    x = 2", "    x: int = 2"))  # a field now
    assert benchmarks_page.code_of(typed) != benchmarks_page.code_of(typed.replace("b: int = 1", "b: int = 2"))
    assert benchmarks_page.code_of(typed) != benchmarks_page.code_of(typed.replace("    y: str\n", ""))
    assert benchmarks_page.code_of(plain) != benchmarks_page.code_of("import torch\n" + plain)
    assert benchmarks_page.code_of(typed) != benchmarks_page.code_of(typed.replace("if TYPE_CHECKING:", "if True:"))


def test_the_check_says_it_cannot_tell_staleness_in_a_clone_without_the_recorded_commits(tmp_path, monkeypatch, capsys):
    repo = tmp_path / "repo"
    (repo / "benchmarks" / "results").mkdir(parents=True)
    row = {
        "metric": "m_a",
        "value": 1.0,
        "unit": "px",
        "commit": "0" * 40,
        "date": "2026-01-01",
        "machine": {"load_start": 0.1, "load_end": 0.2},
    }
    (repo / "benchmarks" / "results" / "geometry.jsonl").write_text(json.dumps(row) + "\n")
    git(repo, "init", "-q")
    git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "one", "--allow-empty")
    monkeypatch.setattr(benchmarks_page, "REPO", repo)
    monkeypatch.setattr(benchmarks_page, "RESULTS", repo / "benchmarks" / "results")
    monkeypatch.setattr(benchmarks_page, "PAGE", repo / "docs" / "benchmarks.md")  # no page at all
    assert benchmarks_page.missing_commits() == ["0" * 40]
    assert benchmarks_page.main(["--check"]) == 0
    assert "lacks 1 recorded commits" in capsys.readouterr().err
    git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "two", "--allow-empty")
    row["commit"] = git(repo, "rev-parse", "HEAD")
    (repo / "benchmarks" / "results" / "geometry.jsonl").write_text(json.dumps(row) + "\n")
    assert benchmarks_page.missing_commits() == [] and benchmarks_page.main(["--check"]) == 1  # the page is missing
