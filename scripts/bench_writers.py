"""Writer costs: CPU ms per frame of every output writer, per setting, at the demo's sizes.

    python scripts/bench.py writers --json [--clip PATH] [--frames 48] [--threads N] [--stream-only]
    python scripts/bench_writers.py [--work DIR] [...]       (the same JSON lines, without the dispatcher)

Content: the first ``--frames`` frames of ``--clip`` (default: the demo clip ``live.mp4`` of the
fixture set that ``bench.py e2e`` maps, generated under ``--work`` once). The *result* stream is
those frames scaled to the demo target's 600x800 (W x H) and held as half floats in [0, 1], what
``synthesis.synthesize`` emits; its face mask is a soft ellipse. The *performer* stream is the
clip's frames as decoded (uint8).

CPU time is ``time.process_time`` (all the process's threads) over the frames, divided by their
count: the share of the 2-core budget a writer takes, which the machine's load disturbs less than
wall time. Each figure is the best of ``--repeats`` runs. Rows (all per frame):

- ``writers_x264_ms_<preset>``, ``writers_x264_psnr_db_<preset>``, ``writers_x264_kb_<preset>``:
  ``write.video``'s encoder on the result (crf 18, 1 thread): CPU ms, PSNR of the decoded RGB
  frames against the frames encoded (dB), file size (kB per frame).
- ``writers_preview_ms_<scale>_<preset>``: ``preview.side_by_side`` plus its encode (crf 20,
  1 thread) at scale 1.0 with ``medium`` (before) and at the stage defaults (after).
- ``writers_exr_ms_<compression>``, ``writers_exr_mb_<compression>``: ``write.exr`` (sRGB decode,
  premultiply, half conversion, compression, atomic rename) with one writer thread and OpenEXR's
  own pool off: CPU ms and MB per frame (``zip``, ``zips``, ``none``: the numpy + zlib-ng writer at
  the default level; ``piz``, ``rle``: OpenImageIO).
- ``writers_exr_ms_zip_level<L>``, ``writers_exr_mb_zip_level<L>``: the same with ``zip`` at each
  deflate level L (1-9).
- ``writers_exr_ms_<zip|zip1|none>_oiio``, ``writers_exr_mb_<zip|zip1|none>_oiio``: the writer before,
  OpenImageIO for every codec, on the same frames in the same run (``zip`` at OpenImageIO's default
  level, ``zip1`` as ``compression="zip:1"``, the stage's level); ``writers_exr_cpu_ratio_<zip|zip1|none>``:
  the stage's CPU ms over that (``zip1``: like with like, both at deflate level 1).
- ``writers_exr_fps_zip_serial`` / ``writers_exr_fps_zip_<N>threads``: wall frames/s of
  ``write.exr`` serial and at the stage's default (N frames in parallel, OpenEXR's pool on);
  ``writers_exr_fps_zip1_oiio_<N>threads``: OpenImageIO at ``zip:1`` frame by frame with OpenEXR's
  pool of N threads, and ``writers_exr_fps_ratio_zip1_<N>threads`` the stage's wall frames/s over it.
- ``writers_stream_ms_<exr|video|preview>``, ``writers_stream_ms_total``: the writers of the
  ``bench.py e2e`` run stage by stage as the pipeline runs them (``pipeline_paper.yaml``'s
  parameters, stage defaults, 16-frame chunks, the EXR with one writer thread): ``write.exr``,
  ``write.video`` of the half-float result, ``preview.side_by_side`` with its encode.
  ``--stream-only`` gives just these rows.
- ``writers_total_ms_before`` / ``writers_total_ms``: result encode + preview + EXR (zip), with
  the settings before this design (``medium``, full-size preview) and with the defaults.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import OpenImageIO as oiio

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from runner.stage import Context, StreamInfo
from stages.video import VideoWriter, X264_PRESETS
from stages.writers.exr import (
    COMPRESSIONS,
    WriteExr,
    exr_name,
    frame_attributes,
    oiio_write_exr,
    to_linear_rgba,
)
from stages.writers.exr_file import ZIP_LEVEL, ZIP_LEVELS
from stages.writers.preview import SideBySide

WIDTH, HEIGHT = 600, 800  # the demo target's size (W x H)
PRESETS = X264_PRESETS[: X264_PRESETS.index("medium") + 1]  # ultrafast .. medium (x264's default)
# write.video's parameters for the result and the preview in pipeline_paper.yaml (bench.py e2e's run).
RESULT_PARAMS = {"codec": "h264", "crf": 18, "filename": "result"}
PREVIEW_PARAMS = {"codec": "h264", "crf": 20, "filename": "preview", "preset": "ultrafast", "threads": 1}


def clip_frames(clip: Path, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """The first ``frames`` frames of ``clip``: ``(performer (T, h, w, 3) uint8, result (T, 800,
    600, 3) float16 sRGB in [0, 1])``, the result being the performer scaled to the target's size."""
    import cv2

    from stages.video import VideoDecode

    performer = VideoDecode().process(0, frames, {"video": clip}, {}, None)["frames"]
    scaled = [cv2.resize(f, (WIDTH, HEIGHT), interpolation=cv2.INTER_LINEAR) for f in performer]
    return performer, (np.stack(scaled) / np.float32(255)).astype(np.float16)


def face_mask(frames: int) -> np.ndarray:
    """A soft elliptical face mask ``(T, 800, 600, 1)`` float16 in [0, 1]."""
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float32)
    r = np.hypot((x - WIDTH / 2) / (0.35 * WIDTH), (y - HEIGHT / 2) / (0.4 * HEIGHT))
    alpha = np.clip((1.1 - r) * 10, 0, 1).astype(np.float16)[None, :, :, None]
    return np.repeat(alpha, frames, axis=0)


CHUNK = 16  # frames per chunk, as pipeline_paper.yaml's chunk_frames


def _stream(frames: np.ndarray, fps: float = 30.0) -> SimpleNamespace:
    info = StreamInfo(frames=len(frames), fps=fps, width=frames.shape[2], height=frames.shape[1])
    return SimpleNamespace(
        info=info,
        read=lambda start, stop: frames[start:stop],
        chunks=lambda: ((start, frames[start : start + CHUNK]) for start in range(0, len(frames), CHUNK)),
    )


def best_of(repeats: int, work: Callable[[], Any]) -> tuple[float, float, Any]:
    """``(cpu s, wall s, result)`` of the run of ``work`` with the least CPU time."""
    best = (np.inf, np.inf, None)
    for _ in range(repeats):
        cpu, wall = time.process_time(), time.perf_counter()
        result = work()
        cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
        if cpu < best[0]:
            best = (cpu, wall, result)
    return best


def encode(path: Path, frames: np.ndarray, *, preset: str, crf: int) -> None:
    """``write.video``'s encoder (1 thread) over uint8 ``frames``."""
    with VideoWriter(path, fps=30.0, width=frames.shape[2], height=frames.shape[1], crf=crf, preset=preset, threads=1) as writer:
        writer.write(frames)


def psnr_db(path: Path, frames: np.ndarray) -> float:
    """PSNR (dB, peak 255) of ``path``'s decoded RGB frames against ``frames``."""
    import av

    with av.open(str(path)) as container:
        decoded = np.stack([f.to_ndarray(format="rgb24") for f in container.decode(video=0)])
    mse = np.mean((decoded.astype(np.float64) - frames) ** 2)
    return float(10 * np.log10(255.0**2 / mse))


def x264_rows(result: np.ndarray, work: Path, repeats: int) -> list[dict]:
    """Result encode per preset: CPU ms, PSNR, kB per frame."""
    from stages.color import to_uint8
    from stages.writers.lut import apply_elementwise

    frames = apply_elementwise(to_uint8, result)
    rows = []
    for preset in PRESETS:
        path = work / f"result_{preset}.mp4"
        cpu, _, _ = best_of(repeats, lambda: encode(path, frames, preset=preset, crf=18))
        rows += [
            _row(f"writers_x264_ms_{preset}", 1e3 * cpu / len(frames), "ms/frame"),
            _row(f"writers_x264_psnr_db_{preset}", psnr_db(path, frames), "dB"),
            _row(f"writers_x264_kb_{preset}", path.stat().st_size / 1e3 / len(frames), "kB/frame"),
        ]
    return rows


def preview_ms(performer: np.ndarray, result: np.ndarray, work: Path, *, scale: float, preset: str, repeats: int) -> float:
    """CPU ms per frame of ``preview.side_by_side`` at ``scale`` and its encode with ``preset``."""
    stage, params = SideBySide(), {"height": 0, "scale": scale}
    inputs = {"performer": _stream(performer), "result": _stream(result)}

    def run() -> None:
        frames = stage.process(0, len(result), inputs, params, None)["frames"]
        encode(work / "preview.mp4", frames, preset=preset, crf=20)

    return 1e3 * best_of(repeats, run)[0] / len(result)


def write_exr(
    srgb: np.ndarray, alpha: np.ndarray, folder: Path, *, threads: int, compression: str, zip_level: int = ZIP_LEVEL
) -> None:
    """One ``write.exr`` chunk over all of ``srgb`` into an emptied ``folder``."""
    shutil.rmtree(folder, ignore_errors=True)
    ctx = Context(device="cpu", files_dir=lambda port: folder)
    inputs = {"frames": _stream(srgb), "mask": _stream(alpha)}
    params = {"compression": compression, "zip_level": zip_level, "threads": threads}
    WriteExr().process(0, len(srgb), inputs, params, ctx)


def write_exr_oiio(srgb: np.ndarray, alpha: np.ndarray, folder: Path, *, compression: str) -> None:
    """The writer before, frame by frame into an emptied ``folder``: the same RGBA and attributes,
    written by OpenImageIO (as ``write.exr`` did for every codec)."""
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    for i in range(len(srgb)):
        oiio_write_exr(
            folder / exr_name(i),
            to_linear_rgba(srgb[i], alpha[i]),
            attributes=frame_attributes(i, fps=30.0),
            compression=compression,
        )


def exr_rows(result: np.ndarray, work: Path, repeats: int, threads: int) -> list[dict]:
    """``write.exr`` CPU ms and MB per frame per compression and zip level (serial), the writer
    before on ``zip`` and ``none`` and the ratios, and zip's wall frames/s."""
    alpha = face_mask(len(result))
    folder = work / "exr"
    pool = oiio.get_int_attribute("exr_threads")

    def measure(name: str, work: Callable[[], Any]) -> tuple[list[dict], float, float]:
        """Rows ``writers_exr_ms_<name>``, ``writers_exr_mb_<name>``; CPU ms and wall s per frame."""
        cpu, wall, _ = best_of(repeats, work)
        size = sum(p.stat().st_size for p in folder.glob("*.exr")) / len(result)
        ms = 1e3 * cpu / len(result)
        rows = [_row(f"writers_exr_ms_{name}", ms, "ms/frame"), _row(f"writers_exr_mb_{name}", size / 1e6, "MB/frame")]
        return rows, ms, wall / len(result)

    rows, ms = [], {}
    try:
        oiio.attribute("exr_threads", 1)  # OpenEXR's own pool off: one core's work
        for compression in COMPRESSIONS:
            new, ms[compression], wall = measure(
                compression, lambda: write_exr(result, alpha, folder, threads=1, compression=compression)
            )
            rows += new
            if compression == "zip":
                rows.append(_row("writers_exr_fps_zip_serial", 1 / wall, "frames/s"))
        for level in ZIP_LEVELS:
            rows += measure(
                f"zip_level{level}", lambda: write_exr(result, alpha, folder, threads=1, compression="zip", zip_level=level)
            )[0]
        for name, codec, own in (("zip", "zip", "zip"), ("zip1", f"zip:{ZIP_LEVEL}", "zip"), ("none", "none", "none")):
            before, ms_before, _ = measure(f"{name}_oiio", lambda: write_exr_oiio(result, alpha, folder, compression=codec))
            rows += before + [_row(f"writers_exr_cpu_ratio_{name}", ms[own] / ms_before, "after/before")]
        oiio.attribute("exr_threads", threads)
        _, wall_oiio, _ = best_of(repeats, lambda: write_exr_oiio(result, alpha, folder, compression=f"zip:{ZIP_LEVEL}"))
    finally:
        oiio.attribute("exr_threads", pool)
    _, wall, _ = best_of(repeats, lambda: write_exr(result, alpha, folder, threads=threads, compression="zip"))
    rows += [
        _row(f"writers_exr_fps_zip_{threads}threads", len(result) / wall, "frames/s"),
        _row(f"writers_exr_fps_zip1_oiio_{threads}threads", len(result) / wall_oiio, "frames/s"),
        _row(f"writers_exr_fps_ratio_zip1_{threads}threads", wall_oiio / wall, "after/before"),
    ]
    shutil.rmtree(folder, ignore_errors=True)
    return rows


def stream_rows(performer: np.ndarray, result: np.ndarray, work: Path, repeats: int) -> list[dict]:
    """The writers of ``bench.py e2e``'s run, stage by stage with ``pipeline_paper.yaml``'s
    parameters and the stage defaults, in 16-frame chunks: CPU ms per frame of ``exr``
    (``write.exr``, one writer thread), ``video`` (``write.video`` of the half-float result,
    ``RESULT_PARAMS``) and ``preview`` (``preview.side_by_side`` and ``write.video`` of it,
    ``PREVIEW_PARAMS``: ``ultrafast``, one thread)."""
    from stages.video import WriteVideo

    alpha = face_mask(len(result))
    video_defaults = {param.name: param.default for param in WriteVideo.params}
    side_defaults = {param.name: param.default for param in SideBySide.params}
    ctx = Context(device="cpu", files_dir=lambda port: work)

    def video(frames: Any, **params: Any) -> None:
        WriteVideo().run({"frames": frames}, {**video_defaults, **params}, ctx)

    def preview() -> None:
        stage, inputs = SideBySide(), {"performer": _stream(performer), "result": _stream(result)}
        info = stage.stream_info(inputs, side_defaults)
        chunks = (
            (start, stage.process(start, min(start + CHUNK, len(result)), inputs, side_defaults, None)["frames"])
            for start in range(0, len(result), CHUNK)
        )
        video(SimpleNamespace(info=info, chunks=lambda: chunks), **PREVIEW_PARAMS)

    parts = {
        "exr": lambda: write_exr(result, alpha, work / "exr", threads=1, compression="zip"),
        "video": lambda: video(_stream(result), **RESULT_PARAMS),
        "preview": preview,
    }
    ms = {name: 1e3 * best_of(repeats, part)[0] / len(result) for name, part in parts.items()}
    shutil.rmtree(work / "exr", ignore_errors=True)
    return [_row(f"writers_stream_ms_{name}", value, "ms/frame") for name, value in ms.items()] + [
        _row("writers_stream_ms_total", sum(ms.values()), "ms/frame")
    ]


def _row(metric: str, value: float, unit: str) -> dict:
    return {"bench": "writers", "metric": metric, "value": value, "unit": unit}


def run(args: argparse.Namespace) -> list[dict]:
    parser = argparse.ArgumentParser(prog="bench writers")
    parser.add_argument("--clip", type=Path, help="performer clip (default: the e2e demo clip live.mp4)")
    parser.add_argument("--frames", type=int, default=48, help="frames written per run")
    parser.add_argument("--repeats", type=int, default=2, help="runs per figure (the least CPU time is kept)")
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1, help="N of the N-thread EXR figure")
    parser.add_argument("--stream-only", action="store_true", help="only the writers_stream_ms_* rows")
    opts = parser.parse_args(getattr(args, "extra", []))
    work = Path(args.work) / "writers"
    work.mkdir(parents=True, exist_ok=True)
    clip = opts.clip
    if clip is None:
        from scripts.bench_geometry import fixture_set

        clip = fixture_set(None, Path(args.work), demo=True) / "clips" / "live.mp4"
    performer, result = clip_frames(clip, opts.frames)
    rows = stream_rows(performer, result, work, opts.repeats)
    if opts.stream_only:
        return rows
    rows += x264_rows(result, work, opts.repeats)
    defaults = {param.name: param.default for param in SideBySide.params}
    from stages.video import WriteVideo

    preset = next(param.default for param in WriteVideo.params if param.name == "preset")
    before = preview_ms(performer, result, work, scale=1.0, preset="medium", repeats=opts.repeats)
    after = preview_ms(performer, result, work, scale=defaults["scale"], preset=preset, repeats=opts.repeats)
    rows += [
        _row("writers_preview_ms_1.0_medium", before, "ms/frame"),
        _row(f"writers_preview_ms_{defaults['scale']}_{preset}", after, "ms/frame"),
    ]
    rows += exr_rows(result, work, opts.repeats, opts.threads)
    value = {r["metric"]: r["value"] for r in rows}
    rows += [
        _row("writers_total_ms_before", value["writers_x264_ms_medium"] + before + value["writers_exr_ms_zip"], "ms/frame"),
        _row("writers_total_ms", value[f"writers_x264_ms_{preset}"] + after + value["writers_exr_ms_zip"], "ms/frame"),
    ]
    return rows


if __name__ == "__main__":
    cli = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    cli.add_argument("--work", type=Path, default=Path(".cache/bench"))
    known, extra = cli.parse_known_args()
    known.extra = extra
    for row in run(known):
        print(json.dumps(row), flush=True)
