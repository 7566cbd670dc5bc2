"""Benchmarks: `python scripts/bench.py AREA [--json] [--record]`.

Each area lives in `scripts/bench_<area>.py` and exposes `run(args) -> list[dict]`, one dict per
metric: {"bench": AREA, "metric": NAME, "value": X, "unit": U}. With --json they are printed
one JSON object per line; without, as a short table. With --record they are also
appended to `benchmarks/results/AREA.jsonl` with what the figures depend on: the commit (with
`-dirty` when tracked files differ from it), the date, the command line, and the machine (cores,
the 1-minute load average at the start and the end); `python scripts/benchmarks_page.py` renders
`docs/benchmarks.md` from the records.
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

AREAS = (
    "runner",
    "geometry",
    "propagation",
    "synthesis",
    "writers",
    "e2e",
    "landmarks",
    "smoothing",
    "real",
    "editor",
    "eigen",
    "reenact",
    "render3d",
    "batch",
    "photo_identity",
    "shot",
    "seen",
)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("area", choices=AREAS)
    parser.add_argument("--json", action="store_true", help="print JSON lines only")
    parser.add_argument("--work", type=Path, default=Path(".cache/bench"), help="scratch folder for generated data")
    parser.add_argument("--record", action="store_true", help="append the rows to benchmarks/results/AREA.jsonl")
    args, rest = parser.parse_known_args(argv)
    args.extra = rest
    sys.path.insert(0, str(REPO))
    module = importlib.import_module(f"scripts.bench_{args.area}")
    started = {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "load_start": os.getloadavg()[0],
        "commit": commit(),
    }
    rows = module.run(args)
    if args.record:
        record(args.area, rows, started, argv if argv is not None else sys.argv[1:])
    if args.json:
        for row in rows:
            print(json.dumps(row), flush=True)
    else:
        width = max(len(r["metric"]) for r in rows)
        for r in rows:
            value = r["value"]
            shown = f"{value:.4g}" if isinstance(value, float) else str(value)
            print(f"{r['metric']:<{width}}  {shown:>12} {r['unit']}")
    return 0


RECORDING_OUTPUTS = (":(exclude)benchmarks/results", ":(exclude)docs/benchmarks.md")  # pathspecs


def commit() -> str:
    """The checkout's commit, ``-dirty`` when a tracked file differs from it (the records and the
    page rendered from them aside: recording writes them); ``unknown`` outside git."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "--", ".", *RECORDING_OUTPUTS],
            cwd=REPO,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("-dirty" if dirty else "")


def record(area: str, rows: list[dict], started: dict, argv: list[str]) -> Path:
    """Append ``rows`` to ``benchmarks/results/<area>.jsonl``, each with the run's provenance."""
    path = REPO / "benchmarks" / "results" / f"{area}.jsonl"
    path.parent.mkdir(parents=True, exist_ok=True)
    machine = {
        "cores": os.cpu_count(),
        "load_start": round(started["load_start"], 2),
        "load_end": round(os.getloadavg()[0], 2),
        "platform": platform.platform(),
        "python": platform.python_version(),
    }
    run = {
        "commit": started["commit"],
        "date": started["date"],
        "command": " ".join(["scripts/bench.py", *argv]),
        "machine": machine,
    }
    with path.open("a", encoding="utf-8") as out:
        for row in rows:
            out.write(json.dumps({**row, **run}, sort_keys=True) + "\n")
    return path


if __name__ == "__main__":
    raise SystemExit(main())
