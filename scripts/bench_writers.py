"""Writer throughput: EXR frames/s at 600x800 with 1 thread and with N threads, per compression.

Runs the ``write.exr`` stage itself (sRGB decode, premultiply, half conversion, compression,
atomic rename) on a synthetic face-like chunk, in three configurations:

* ``serial``: 1 writer thread, OpenEXR's own thread pool off (``exr_threads`` = 1) — the baseline;
* ``1thread``: 1 writer thread, OpenEXR compressing a file's line blocks on its default pool;
* ``<N>threads``: N frames written in parallel by the stage's pool (the stage's default).

Ratios are against ``serial`` measured in the same run.

    python scripts/bench.py writers --json [--frames 24] [--threads N]
    python scripts/bench_writers.py          (the same JSON lines, without the dispatcher)
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import OpenImageIO as oiio

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from runner.stage import Context, StreamInfo  # noqa: E402
from stages.writers.exr import WriteExr  # noqa: E402

WIDTH, HEIGHT = 600, 800


def synthetic_chunk(frames: int, *, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Smooth shading plus fine noise (skin-like texture) and a soft elliptical face mask.

    Returns ``(srgb (T, H, W, 3) float32 in [0, 1], alpha (T, H, W, 1) float32)``.
    """
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float32)
    base = np.stack([0.55 + 0.3 * x / WIDTH, 0.4 + 0.2 * y / HEIGHT, 0.35 + 0.1 * np.sin(x / 37)], axis=2)
    srgb = np.clip(base + rng.normal(0, 0.02, (frames, HEIGHT, WIDTH, 3)), 0, 1).astype(np.float32)
    r = np.hypot((x - WIDTH / 2) / (0.35 * WIDTH), (y - HEIGHT / 2) / (0.4 * HEIGHT))
    alpha = np.clip((1.1 - r) * 10, 0, 1).astype(np.float32)[None, :, :, None]
    return srgb, np.repeat(alpha, frames, axis=0)


def _stream(frames: np.ndarray, fps: float = 30.0) -> SimpleNamespace:
    info = StreamInfo(frames=len(frames), fps=fps, width=frames.shape[2], height=frames.shape[1])
    return SimpleNamespace(info=info, read=lambda start, stop: frames[start:stop])


def exr_fps(srgb: np.ndarray, alpha: np.ndarray, *, threads: int, compression: str, work: Path) -> float:
    """Frames per second of one ``write.exr`` chunk over all of ``srgb``, best of two runs."""
    inputs = {"frames": _stream(srgb), "mask": _stream(alpha)}
    best = np.inf
    for _ in range(2):
        folder = work / f"exr_{compression}_{threads}"
        shutil.rmtree(folder, ignore_errors=True)
        ctx = Context(device="cpu", files_dir=lambda port: folder)
        t0 = time.perf_counter()
        WriteExr().process(0, len(srgb), inputs, {"compression": compression, "threads": threads}, ctx)
        best = min(best, time.perf_counter() - t0)
    shutil.rmtree(work / f"exr_{compression}_{threads}", ignore_errors=True)
    return len(srgb) / best


def _row(metric: str, value: float, unit: str) -> dict:
    return {"bench": "writers", "metric": metric, "value": value, "unit": unit}


def run(args: argparse.Namespace) -> list[dict]:
    parser = argparse.ArgumentParser(prog="bench writers")
    parser.add_argument("--frames", type=int, default=24, help="frames in the chunk")
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1, help="N of the N-thread figure")
    opts = parser.parse_args(getattr(args, "extra", []))
    work = Path(args.work) / "writers"
    work.mkdir(parents=True, exist_ok=True)
    srgb, alpha = synthetic_chunk(opts.frames)
    exr_threads = oiio.get_int_attribute("exr_threads")
    rows = []
    for compression in ("zip", "piz"):
        oiio.attribute("exr_threads", 1)
        serial = exr_fps(srgb, alpha, threads=1, compression=compression, work=work)
        oiio.attribute("exr_threads", exr_threads)
        fps = {
            "serial": serial,
            "1thread": exr_fps(srgb, alpha, threads=1, compression=compression, work=work),
            f"{opts.threads}threads": exr_fps(srgb, alpha, threads=opts.threads, compression=compression, work=work),
        }
        for name, value in fps.items():
            rows.append(_row(f"exr_fps_{compression}_{name}", value, "frames/s"))
        for name, value in list(fps.items())[1:]:
            rows.append(_row(f"exr_speedup_{compression}_{name}", value / serial, "x"))
    return rows


if __name__ == "__main__":
    cli = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    cli.add_argument("--work", type=Path, default=Path(".cache/bench"))
    known, extra = cli.parse_known_args()
    known.extra = extra
    for row in run(known):
        print(json.dumps(row), flush=True)
