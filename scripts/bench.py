"""Benchmarks: `python scripts/bench.py AREA [--json]`.

Each area lives in `scripts/bench_<area>.py` and exposes `run(args) -> list[dict]`, one dict per
metric: {"bench": AREA, "metric": NAME, "value": X, "unit": U}. With --json they are printed
one JSON object per line (DESIGN.md); without, as a short table.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from pathlib import Path

AREAS = ("runner", "geometry", "propagation", "synthesis", "writers", "e2e", "landmarks", "smoothing", "real", "editor", "eigen", "reenact", "render3d", "batch", "photo_identity", "shot")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("area", choices=AREAS)
    parser.add_argument("--json", action="store_true", help="print JSON lines only")
    parser.add_argument("--work", type=Path, default=Path(".cache/bench"), help="scratch folder for generated data")
    args, rest = parser.parse_known_args(argv)
    args.extra = rest
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    module = importlib.import_module(f"scripts.bench_{args.area}")
    rows = module.run(args)
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


if __name__ == "__main__":
    raise SystemExit(main())
