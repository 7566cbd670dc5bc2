"""Runner benchmarks: `python scripts/bench.py runner [--json] [--work DIR]`.

Metrics (one clip, generated under ``args.work``: 300 frames, 640x480, H.264):

- ``decode_fps``: ``video.decode`` reading the clip chunk by chunk; ``decode_vs_pyav_ratio`` is
  its time over a bare PyAV decode loop (``to_ndarray("rgb24")``) measured in the same run.
- ``runner_overhead_ratio``: ``runner run`` of decode -> image.gray -> write.video on an empty
  cache (in this process, so interpreter start-up is not counted) over the same stage code
  called directly in a loop (decode chunk, VideoWriter.write); target < 1.10. The
  runner streams gray's chunks into the encoder as it computes and stores them (see
  docs/runner.md, *Scheduling*), so x264's threads overlap the Python work as in the loop.
- ``runner_noop_rerun_s``: wall time of a fully cached re-run of the same pipeline, as a user
  sees it: a new ``runner`` process, start-up included; target < 1 s.
- ``runner_cli_startup_s``: wall time of ``runner dag pipeline.yaml`` (the repository's
  pipeline) in a new process: start-up, importing the used stages' modules to read their
  declarations, loading and validating the graph; target < 0.5 s.
- ``runner_cached_pipeline_rerun_s``: wall time of ``runner run pipeline.yaml`` on the live CI
  clip (``fixtures/clips/live.mp4``) with everything cached, in a new process; target < 1 s.
  The first call computes the cache (kept under ``--work``), which takes minutes. The
  ``*_cpu_s`` variants are the child process's CPU time, which other people's load disturbs
  much less than wall time.

Each timing is the best of ``REPEATS`` runs, the two sides of a ratio interleaved, because the
machine is shared: wall times move with other people's load. The ``*_cpu`` variants use CPU time
(this process and its threads, or the child process), which load disturbs much less.
"""

from __future__ import annotations

import contextlib
import io
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from runner.registry import Registry  # noqa: E402
from scripts.make_test_clip import write_clip  # noqa: E402
from stages.color import luma_opencv  # noqa: E402
from stages.video import VideoDecode, VideoWriter, WriteVideo, probe  # noqa: E402

FRAMES, WIDTH, HEIGHT, CHUNK = 300, 640, 480, 16
REPEATS = 3
BUILTINS = {
    "video.decode": "stages.video:VideoDecode",
    "image.gray": "stages.video:ImageGray",
    "write.video": "stages.video:WriteVideo",
}
CHAIN = f"""chunk_frames: {CHUNK}
inputs:
  clip: {{type: video}}
stages:
  decode: {{uses: video.decode, inputs: {{video: clip}}}}
  gray: {{uses: image.gray, inputs: {{frames: decode.frames}}}}
  write: {{uses: write.video, params: {{codec: h264, crf: 18}}, inputs: {{frames: gray.frames}}}}
"""


def _timed(fn) -> tuple[float, float]:
    """(wall s, CPU s) of one call; CPU time covers this process's threads and its children."""

    def cpu() -> float:
        children = os.times()
        return time.process_time() + children.children_user + children.children_system

    wall, started = time.perf_counter(), cpu()
    fn()
    return time.perf_counter() - wall, cpu() - started


def _best(*fns) -> list[tuple[float, float]]:
    """Best (wall, CPU) of each function over ``REPEATS`` interleaved rounds."""
    rounds = [[_timed(fn) for fn in fns] for _ in range(REPEATS)]
    return [(min(r[i][0] for r in rounds), min(r[i][1] for r in rounds)) for i in range(len(fns))]


def _plugin_site(work: Path) -> Path | None:
    """A dist-info registering the built-in video stages, needed only while the installed
    package does not register them yet."""
    if all(name in Registry.from_entry_points() for name in BUILTINS):
        return None
    info = work / "site" / "runner_bench_builtins-0.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: runner-bench-builtins\nVersion: 0\n")
    body = "\n".join(f"{k} = {v}" for k, v in BUILTINS.items())
    (info / "entry_points.txt").write_text(f"[expression_mapping.stages]\n{body}\n")
    return info.parent


def _direct(clip: Path, out: Path) -> None:
    """The chain without the runner: the same stage code in a plain loop, encoding with
    ``CHAIN``'s crf and ``write.video``'s default preset and threads."""
    info = probe(clip)
    decode = VideoDecode()
    defaults = {param.name: param.default for param in WriteVideo.params if param.name in ("preset", "threads")}
    with VideoWriter(out, fps=info.fps, width=info.width, height=info.height, codec="h264", crf=18, **defaults) as writer:
        for start in range(0, info.frames, CHUNK):
            frames = decode.process(start, min(start + CHUNK, info.frames), {"video": clip}, {}, None)["frames"]
            writer.write(luma_opencv(frames)[..., None])


def _decode_pyav(clip: Path) -> None:
    import av

    with av.open(str(clip)) as container:
        for frame in container.decode(video=0):
            frame.to_ndarray(format="rgb24")


def _decode_stage(clip: Path) -> None:
    decode = VideoDecode()
    for start in range(0, FRAMES, CHUNK):
        decode.process(start, min(start + CHUNK, FRAMES), {"video": clip}, {}, None)


def run(args) -> list[dict]:
    work = Path(args.work) / "runner"
    work.mkdir(parents=True, exist_ok=True)
    clip = work / f"clip_{FRAMES}_{WIDTH}x{HEIGHT}.mp4"
    if not clip.exists():
        write_clip(clip, frames=FRAMES, width=WIDTH, height=HEIGHT, crf=23)
    pipeline = work / "chain.yaml"
    pipeline.write_text(CHAIN)
    site = _plugin_site(work)
    if site is not None:
        sys.path.insert(0, str(site))
    from runner.cli import main

    rows = []
    (decode_s, _), (pyav_s, _) = _best(lambda: _decode_stage(clip), lambda: _decode_pyav(clip))
    rows.append({"bench": "runner", "metric": "decode_fps", "value": FRAMES / decode_s, "unit": "fps"})
    rows.append({"bench": "runner", "metric": "decode_vs_pyav_ratio", "value": decode_s / pyav_s, "unit": "x"})

    cache = work / "cache"

    def runner_cold() -> None:
        shutil.rmtree(cache, ignore_errors=True)
        try:
            main(["run", str(pipeline), "--in", str(clip), "--out", str(work / "out"), "--cache-dir", str(cache)])
        except SystemExit as exc:
            if exc.code:
                raise RuntimeError(f"runner exited with {exc.code}") from None

    with contextlib.redirect_stdout(io.StringIO()):
        (direct_s, direct_cpu), (runner_s, runner_cpu) = _best(lambda: _direct(clip, work / "direct.mp4"), runner_cold)
    rows.append({"bench": "runner", "metric": "direct_chain_fps", "value": FRAMES / direct_s, "unit": "fps"})
    rows.append({"bench": "runner", "metric": "runner_chain_fps", "value": FRAMES / runner_s, "unit": "fps"})
    rows.append({"bench": "runner", "metric": "runner_overhead_ratio", "value": runner_s / direct_s, "unit": "x"})
    rows.append({"bench": "runner", "metric": "runner_overhead_cpu_ratio", "value": runner_cpu / direct_cpu, "unit": "x"})

    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(site or ""), str(REPO)]))}
    command = [
        sys.executable,
        "-m",
        "runner.cli",
        "run",
        str(pipeline),
        "--in",
        str(clip),
        "--out",
        str(work / "out"),
        "--cache-dir",
        str(cache),
    ]
    [(rerun_s, rerun_cpu)] = _best(lambda: subprocess.run(command, env=env, check=True, capture_output=True))
    rows.append({"bench": "runner", "metric": "runner_noop_rerun_s", "value": rerun_s, "unit": "s"})
    rows.append({"bench": "runner", "metric": "runner_noop_rerun_cpu_s", "value": rerun_cpu, "unit": "s"})
    return rows + _pipeline_rows(work, env)


def _pipeline_rows(work: Path, env: dict[str, str]) -> list[dict]:
    """Start-up of ``runner dag`` and a fully cached run of the repository's pipeline.yaml on the
    live clip, each a new process (best of ``REPEATS``)."""
    runner = [sys.executable, "-m", "runner.cli"]
    [(dag_s, dag_cpu)] = _best(lambda: _run_checked([*runner, "dag", "pipeline.yaml"], env))
    command = [
        *runner,
        "run",
        "pipeline.yaml",
        "--in",
        "fixtures/clips/live.mp4",
        "--out",
        str(work / "pipeline_out"),
        "--cache-dir",
        str(work / "pipeline_cache"),
    ]
    _run_checked(command, env)  # fills the cache once
    [(rerun_s, rerun_cpu)] = _best(lambda: _run_checked(command, env))
    return [
        {"bench": "runner", "metric": "runner_cli_startup_s", "value": dag_s, "unit": "s"},
        {"bench": "runner", "metric": "runner_cli_startup_cpu_s", "value": dag_cpu, "unit": "s"},
        {"bench": "runner", "metric": "runner_cached_pipeline_rerun_s", "value": rerun_s, "unit": "s"},
        {"bench": "runner", "metric": "runner_cached_pipeline_rerun_cpu_s", "value": rerun_cpu, "unit": "s"},
    ]


def _run_checked(command: list[str], env: dict[str, str]) -> None:
    """Run ``command`` in the repository; RuntimeError with its stderr if it fails."""
    done = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True)
    if done.returncode:
        raise RuntimeError(f"{' '.join(command)} exited with {done.returncode}: {done.stderr.strip()}")
