"""End-to-end benchmark: the default pipeline on the 300-frame 640x480 demo clip.

    python scripts/bench.py e2e [--json] [--work DIR] [--clip calm|live] [--ci] [--default] [--device cuda]

The demo fixture set (600x800 target pack, 640x480 performer clips) is generated under
``--work`` on first use. Each run starts from an empty cache and writes every output of
``pipeline_paper.yaml`` (EXR frames, result and preview mp4, per-frame data): the paper's tracker
path, whose ground truth the demo clips carry. Each run's ``--log-json`` events (per stage: status
and seconds) are kept next to its output folder (``e2e/full/out.log.jsonl``): where the time went.

Metrics
-------
- ``e2e_fps``, ``e2e_frames``: frames per second of the whole pipeline (wall time of the CLI,
  start-up included) and the clip's frame count.
- ``e2e_fps_warponly`` and ``e2e_speed_ratio``: the same pipeline with
  ``synthesize.mode=warp-only`` (traditional expression mapping, no details) measured in the same
  run, and the ratio ``e2e_fps / e2e_fps_warponly`` (the cost of expression details).
- with ``--device cuda``: only ``e2e_fps_cuda``, the full run with ``runner run --device cuda``
  (a GPU machine; on a CPU-only one the runner exits with "CUDA is not available").
- ``e2e_cache_mb``: size of the cache folder after the full run (MB, 10^6 bytes; a file
  hard-linked twice counted once).
- ``e2e_rerun_s``: wall time of a second, fully cached run.
- with ``--default``: ``e2e_fps_default``, the repository's default ``pipeline.yaml`` (a face
  landmarker on the performer instead of the paper's tracker) on the same clip and target pack,
  from an empty cache, every output written.
- ``e2e_target_err_px``: mean distance of the pipeline's target geometry (all points, per frame)
  to the ideal mapping ``target_points`` of the clip's ground truth; ``e2e_target_err_neutral_px``
  the same for the target's neutral left unchanged (a do-nothing baseline).
- with ``--ci``: ``e2e_target_err_px_ci_<clip>`` and ``e2e_target_err_neutral_px_ci_<clip>``, the
  same two figures for the bundled CI fixture clips ``calm`` and ``live`` (``fixtures/``).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent


def row(metric: str, value: float, unit: str) -> dict[str, Any]:
    return {"bench": "e2e", "metric": metric, "value": value, "unit": unit}


def run_pipeline(root: Path, clip: str, out: Path, cache: Path, *extra: str, paper: bool = True) -> float:
    """Run ``pipeline_paper.yaml`` (or, ``paper`` False, the default ``pipeline.yaml``) on
    ``root``'s fixture set; return the wall time in s."""
    tracker = (
        ["--input", f"init={root / 'clips' / f'{clip}_track0.csv'}", "--input", f"performer={root / 'packs' / 'performer'}"]
        if paper
        else []
    )
    command = [
        sys.executable,
        "-c",
        "from runner.cli import main; main()",
        "run",
        str(REPO / ("pipeline_paper.yaml" if paper else "pipeline.yaml")),
        "--in",
        str(root / "clips" / f"{clip}.mp4"),
        *tracker,
        "--input",
        f"target={root / 'packs' / 'target'}",
        "--out",
        str(out),
        "--cache-dir",
        str(cache),
        "--log-json",
        str(out.parent / f"{out.name}.log.jsonl"),
        *extra,
    ]
    out.parent.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    start = time.perf_counter()
    result = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True)
    elapsed = time.perf_counter() - start
    if result.returncode != 0:
        raise SystemExit(f"pipeline failed ({result.returncode}): {result.stderr.strip()}")
    return elapsed


def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(prog="bench.py e2e")
    parser.add_argument("--clip", default="live", choices=("calm", "live"), help="demo clip to map")
    parser.add_argument("--ci", action="store_true", help="also the target geometry error on the CI clips")
    parser.add_argument("--default", action="store_true", help="also frames/s of the default pipeline.yaml")
    parser.add_argument(
        "--device",
        default="cpu",
        choices=("cpu", "cuda"),
        help="cuda: only the full run, with `runner run --device cuda` (row e2e_fps_cuda)",
    )
    options = parser.parse_args(args.extra)
    from scripts.bench_geometry import fixture_set

    work = Path(args.work) / "e2e"
    root = fixture_set(None, Path(args.work), demo=True)
    truth = np.load(root / "clips" / f"{options.clip}_truth.npz")
    frames = len(truth["points"])

    if options.device == "cuda":
        shutil.rmtree(work / "cuda", ignore_errors=True)
        seconds = run_pipeline(
            root,
            options.clip,
            work / "cuda" / "out",
            work / "cuda" / "cache",
            "--device",
            "cuda",
            "--set",
            "synthesize.mode=full",
        )
        return [row("e2e_frames", frames, "frames"), row("e2e_fps_cuda", frames / seconds, "frames/s")]
    timings = {}
    for mode in ("full", "warp-only"):
        shutil.rmtree(work / mode, ignore_errors=True)
        timings[mode] = run_pipeline(
            root, options.clip, work / mode / "out", work / mode / "cache", "--set", f"synthesize.mode={mode}"
        )
        if mode == "full":
            cache_mb = folder_bytes(work / mode / "cache") / 1e6
    rerun = run_pipeline(root, options.clip, work / "full" / "again", work / "full" / "cache", "--set", "synthesize.mode=full")

    fps, fps_warp = frames / timings["full"], frames / timings["warp-only"]
    rows = [
        row("e2e_frames", frames, "frames"),
        row("e2e_fps", fps, "frames/s"),
        row("e2e_fps_warponly", fps_warp, "frames/s"),
        row("e2e_speed_ratio", fps / fps_warp, "ratio"),
        row("e2e_cache_mb", cache_mb, "MB"),
        row("e2e_rerun_s", rerun, "s"),
        *target_errors(root, options.clip, work / "full" / "out", ""),
    ]
    if options.default:
        shutil.rmtree(work / "default", ignore_errors=True)
        seconds = run_pipeline(root, options.clip, work / "default" / "out", work / "default" / "cache", paper=False)
        rows.append(row("e2e_fps_default", frames / seconds, "frames/s"))
    for clip in ("calm", "live") if options.ci else ():
        shutil.rmtree(work / f"ci_{clip}", ignore_errors=True)
        run_pipeline(REPO / "fixtures", clip, work / f"ci_{clip}" / "out", work / f"ci_{clip}" / "cache")
        rows += target_errors(REPO / "fixtures", clip, work / f"ci_{clip}" / "out", f"_ci_{clip}")
    return rows


def folder_bytes(folder: Path) -> int:
    """Bytes of the files under ``folder``, each inode counted once."""
    sizes = {}
    for path in folder.rglob("*"):
        if path.is_file() and not path.is_symlink():
            stat = path.stat()
            sizes[(stat.st_dev, stat.st_ino)] = stat.st_size
    return sum(sizes.values())


def target_errors(root: Path, clip: str, out: Path, suffix: str) -> list[dict[str, Any]]:
    """Mean px distance of the pipeline's target geometry (``out/data/data.npz``) and of the
    target's neutral to the ideal mapping of ``root``'s clip."""
    from stages.actor_pack import load_pack

    ideal = np.load(root / "clips" / f"{clip}_truth.npz")["target_points"]
    data = np.load(out / "data" / "data.npz")
    neutral = load_pack(root / "packs" / "target").neutral.points
    return [
        row(f"e2e_target_err_px{suffix}", float(np.linalg.norm(data["target_xy"] - ideal, axis=-1).mean()), "px"),
        row(f"e2e_target_err_neutral_px{suffix}", float(np.linalg.norm(neutral[None] - ideal, axis=-1).mean()), "px"),
    ]
