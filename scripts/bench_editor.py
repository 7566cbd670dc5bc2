"""Editor benchmark: image updates per second while dragging, in a real browser.

The editor (``python -m editor.cli``) serves the 600x800 demo target with 15 examples (the
target of ``make_fixtures.py --demo``, only its target pack rendered under ``--work``, with
held-out expressions added as examples up to 15). Debian's Chromium, driven by playwright,
drags the lower lip's centre round a small ellipse for ``--seconds``, one pointer move every
``--move-ms``; the page keeps at most two requests in flight and sends only the newest geometry. The page
records, per image drawn, the time since the pointer event whose geometry it shows.

* ``editor_update_fps``: images drawn per second while dragging;
* ``editor_latency_ms_p50``, ``editor_latency_ms_p95``: pointer event -> new image drawn on the
  canvas, ms;
* ``editor_synth_fps``: the synthesis-only rate in the same run, 1000 / median server time per
  image (synthesis and JPEG encoding, without propagation, transfer and decoding);
* ``editor_wait_ms_p50``: request sent -> answer received, less the server's work on it (the
  wait for a renderer and the transfer); ``editor_decode_ms_p50``: answer received ->
  image decoded in the page.

* ``editor_cpu_ms_per_update_{server,renderers,browser,driver}``: CPU time (user + system,
  from ``/proc``) of the editor's server process, its renderer processes, Chromium's processes
  and playwright's driver over the measured drag, divided by the images drawn (what one update
  costs the machine, all of it; the browser's and the driver's share is mostly per pointer event
  and per displayed frame, not per image); ``editor_answers``: image answers received in the
  window, drawn or overtaken by a newer one (work done and not shown: answers - updates).

The drag is measured twice: with the server's defaults (``--preview-scale`` 1: the pipeline's
image at the pack's size on every update, as JPEG) and, as the ``editor_half_*`` rows, with
half-size images while dragging (``--preview-scale 0.5``, the previous default), in the same
run. ``--parts`` measures instead the CPU time of each part of an update in this process
(``editor_part_*`` rows, see :func:`profile_parts`), among them the pipeline's synthesis of one
image (``synth_pipeline``) against the editor's drag image at full size (``synth_drag``).

    python scripts/bench.py editor --json [--pack PACK] [--seconds 8] [--no-half] [--screenshot docs/img/editor.png]

* ``editor_synth_cpu_ms_p50``, ``editor_propagate_cpu_ms_p50``: CPU time of the server's
  renderer per image for synthesis and JPEG encoding, and for motion propagation (with
  one torch thread that is all of it; unlike wall-clock time it hardly grows when other
  processes load the machine, so it tells what an idle machine would do).

The server runs with ``--threads 1`` and ``--processes 2`` (its defaults; ``--processes 0``
here renders on the server's threads, to compare; ``--threads N`` needs ``--processes 0``).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from editor.browser import chromium  # noqa: E402
from editor.cli import spawn  # noqa: E402
from stages.layout import read_yaml  # noqa: E402

EXAMPLES = 15


def bench_pack(work: Path) -> Path:
    """The 600x800 demo target with ``EXAMPLES`` examples, made once under ``work``."""
    from scripts.make_fixtures import DEMO, make_part

    folder = work / "editor_demo" / "target"
    if (folder / "pack.yaml").is_file():
        return folder
    source = work / "editor_demo" / "demo" / "packs" / "target"
    if not (source / "pack.yaml").is_file():
        make_part(source.parent.parent, "pack:target", seed=1, spec=DEMO)
    tmp = folder.with_name("target.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(source, tmp)
    manifest = read_yaml(tmp / "pack.yaml", what="actor pack", noun="manifest")
    with np.load(tmp / "truth.npz", allow_pickle=False) as truth:
        index, images, points, names = (
            truth["heldout_index"],
            truth["heldout_image"],
            truth["captured_points"],
            truth["point_names"],
        )
    extra = [(k, str(image)) for k, image in zip(index, images) if image][: max(EXAMPLES - len(manifest["examples"]), 0)]
    for k, image in extra:
        name = Path(image).stem
        rows = ["name,x,y"] + [f"{n},{x:.6f},{y:.6f}" for n, (x, y) in zip(names, points[k])]
        (tmp / "points" / f"{name}.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
        manifest["examples"].append({"name": name, "image": image, "points": f"points/{name}.csv"})
    (tmp / "pack.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False), encoding="utf-8")
    tmp.rename(folder)
    return folder


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values, np.float64), q)) if values else float("nan")


def process_cpu_s(server: int) -> dict[str, float]:
    """CPU seconds (user + system) so far of this benchmark's descendant processes, by role:
    ``server`` (the editor's server process ``server``), ``renderers`` (its children),
    ``browser`` (Chromium's processes) and ``driver`` (the rest: playwright's driver).
    Read from ``/proc`` (Linux)."""
    tick = os.sysconf("SC_CLK_TCK")
    table = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
            cmdline = (stat.parent / "cmdline").read_bytes()
        except OSError:  # the process ended meanwhile
            continue
        fields = text[text.rindex(")") + 2 :].split()  # after the command name, which may hold spaces
        table[int(stat.parent.name)] = (int(fields[1]), (int(fields[11]) + int(fields[12])) / tick, cmdline)
    mine, grew = {os.getpid()}, True
    while grew:
        found = {pid for pid, (ppid, _, _) in table.items() if ppid in mine} - mine
        mine |= found
        grew = bool(found)
    totals = dict.fromkeys(("server", "renderers", "browser", "driver"), 0.0)
    for pid in mine - {os.getpid()}:
        ppid, cpu, cmdline = table[pid]
        role = "server" if pid == server else "renderers" if ppid == server else "browser" if b"chromium" in cmdline else "driver"
        totals[role] += cpu
    return totals


def drag_session(page, *, point: str, seconds: float, move_ms: float, server: int) -> dict:
    """Drag ``point`` round an ellipse for ``seconds``; the page's stats of that window and the
    CPU time of each process role (:func:`process_cpu_s`) over it."""
    layout = page.evaluate("window.editor.layout()")
    index = layout["names"].index(point)
    x0, y0 = page.evaluate("window.editor.geometry()")[index]
    box = page.locator("#overlay").bounding_box()
    cx, cy = box["x"] + x0 + 0.5, box["y"] + y0 + 0.5
    page.mouse.move(cx, cy)
    page.mouse.down()
    page_start = page.evaluate("performance.now()")
    cpu_start = process_cpu_s(server)
    start = time.perf_counter()
    while (elapsed := time.perf_counter() - start) < seconds:
        phase = 2 * np.pi * elapsed / 2.0
        page.mouse.move(cx + 6.0 * np.sin(phase), cy + 10.0 * (1 - np.cos(phase)))
        time.sleep(move_ms / 1000.0)
    page_end = page.evaluate("performance.now()")
    cpu_end = process_cpu_s(server)
    page.mouse.up()
    page.evaluate("window.editor.idle()")
    stats = page.evaluate("window.editor.stats")
    inside = [k for k, t in enumerate(stats["updates"]) if page_start < t <= page_end]
    return {
        "fps": len(inside) / ((page_end - page_start) / 1000.0),
        "latencies": [stats["latencies"][k] for k in inside],
        "synth_ms": [stats["synthMs"][k] for k in inside],
        "synth_cpu_ms": [stats["synthCpuMs"][k] for k in inside],
        "propagate_cpu_ms": [stats["propagateCpuMs"][k] for k in inside],
        "wait_ms": [stats["waitMs"][k] for k in inside],
        "decode_ms": [stats["decodeMs"][k] for k in inside],
        "errors": stats["errors"],
        "answers": sum(page_start < t <= page_end for t in stats["answers"]),
        "cpu_ms": {role: (cpu_end[role] - cpu_start[role]) * 1e3 for role in cpu_start},
    }


def measure(pack: Path, opts: argparse.Namespace, *, preview_scale: float, screenshot: Path | None = None) -> dict:
    """Serve ``pack`` with ``preview_scale``, drag in Chromium; the stats of the measured drag."""
    process, url = spawn(
        pack, "--threads", str(opts.threads), "--processes", str(opts.processes), "--preview-scale", str(preview_scale)
    )
    try:
        with chromium() as browser:
            page = browser.new_page(viewport={"width": 1000, "height": 840})
            page.goto(url)
            page.wait_for_function("() => window.editor && window.editor.stats.updates.length > 0", timeout=300_000)
            drag_session(page, point=opts.point, seconds=1.0, move_ms=opts.move_ms, server=process.pid)  # warm-up
            page.click("#reset")
            page.evaluate("window.editor.idle()")
            result = drag_session(page, point=opts.point, seconds=opts.seconds, move_ms=opts.move_ms, server=process.pid)
            if screenshot:
                save_screenshot(page, screenshot)
    finally:
        process.terminate()
        process.wait(timeout=30)
    return result


def run(args: argparse.Namespace) -> list[dict]:
    parser = argparse.ArgumentParser(prog="bench.py editor")
    parser.add_argument(
        "--pack", type=Path, help="target pack (default: the 600x800 demo target with 15 examples, made under --work)"
    )
    parser.add_argument("--seconds", type=float, default=8.0, help="dragging time measured")
    parser.add_argument("--move-ms", type=float, default=8.0, help="pause between pointer moves, ms")
    parser.add_argument("--point", default="mouth_outer_12", help="the feature point dragged")
    parser.add_argument("--threads", type=int, default=1, help="torch/OpenCV threads of the server (its --threads)")
    parser.add_argument("--processes", type=int, default=2, help="renderer processes of the server (its --processes; 0: threads)")
    parser.add_argument(
        "--preview-scale", type=float, default=1.0, help="the server's --preview-scale in the first drag (its default 1)"
    )
    parser.add_argument("--no-half", action="store_true", help="skip the second drag with half-size images (--preview-scale 0.5)")
    parser.add_argument("--screenshot", type=Path, help="also save a screenshot of the editor (PNG, subregions shown)")
    parser.add_argument(
        "--parts", action="store_true", help="only the CPU time of each part of an update, in this process (no browser)"
    )
    opts = parser.parse_args(getattr(args, "extra", []))
    pack = opts.pack or bench_pack(Path(args.work))
    row = lambda metric, value, unit: {"bench": "editor", "metric": metric, "value": value, "unit": unit}
    if opts.parts:
        parts = profile_parts(pack, point=opts.point)
        return [row(f"editor_part_{name}_cpu_ms", value, "ms") for name, value in parts.items()] + [
            row("editor_part_load_avg", os.getloadavg()[0], "processes")
        ]
    runs = [("editor", opts.preview_scale)] + ([] if opts.no_half else [("editor_half", 0.5)])
    rows = []
    for prefix, scale in runs:
        result = measure(pack, opts, preview_scale=scale, screenshot=opts.screenshot if prefix == "editor" else None)
        rows += [
            row(f"{prefix}_update_fps", result["fps"], "images/s"),
            row(f"{prefix}_latency_ms_p50", percentile(result["latencies"], 50), "ms"),
            row(f"{prefix}_latency_ms_p95", percentile(result["latencies"], 95), "ms"),
            row(f"{prefix}_synth_fps", 1000.0 / percentile(result["synth_ms"], 50), "images/s"),
            row(f"{prefix}_synth_cpu_ms_p50", percentile(result["synth_cpu_ms"], 50), "ms"),
            row(f"{prefix}_propagate_cpu_ms_p50", percentile(result["propagate_cpu_ms"], 50), "ms"),
            row(f"{prefix}_wait_ms_p50", percentile(result["wait_ms"], 50), "ms"),
            row(f"{prefix}_decode_ms_p50", percentile(result["decode_ms"], 50), "ms"),
            row(f"{prefix}_updates", len(result["latencies"]), "images"),
            row(f"{prefix}_answers", result["answers"], "images"),
            *[
                row(f"{prefix}_cpu_ms_per_update_{role}", ms / max(len(result["latencies"]), 1), "ms")
                for role, ms in result["cpu_ms"].items()
            ],
            row(f"{prefix}_errors", result["errors"], "responses"),
            row(f"{prefix}_preview_scale", scale, "fraction"),
            row(f"{prefix}_load_avg", os.getloadavg()[0], "processes"),
        ]
    return rows


def profile_parts(pack: Path, *, point: str, repeats: int = 15) -> dict[str, float]:
    """Median CPU time (ms, this thread, one torch thread) of each part of an update, over
    geometries of ``point`` dragged round the benchmark's ellipse, the parts taking turns.

    ``propagate``: motion propagation (the library's ``propagate_edit``); ``propagate_drag``: the
    same with the pinned set's sweeps recorded (:mod:`stages.propagation.pinned`, what the editor runs;
    the recording is made before the timing); ``qp``: the per-subregion QPs; ``composite_pipeline``:
    compositing the whole image (the pipeline's synthesis); ``composite_drag``: compositing the
    face box only (the drag image, :mod:`editor.preview`); ``synth_pipeline``: the pipeline's
    whole synthesis (QP, compositing, warp of colour and alpha, clamping); ``synth_drag``: the
    drag image at the pack's size (QP, face-box compositing, warp of colour); ``uint8``: the
    8-bit conversion; ``jpeg``, ``png``: encoding the 8-bit image. The warp is about ``synth -
    qp - composite``.
    """
    import cv2
    import torch

    from editor.engine import EditorEngine, encode, to_uint8
    from editor.geometry import edited_geometry
    from stages.synthesis.composite import composite

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    engine = EditorEngine(pack)
    synth, previewer = engine.synthesizer, engine.previewer
    index = engine.layout.point_names.index(point)
    neutral = engine.pca.neutral
    pinned = [{index: neutral[index] + [6.0 * np.sin(t), 10.0 * (1 - np.cos(t))]} for t in np.linspace(0, 2 * np.pi, repeats)]
    points = [edited_geometry(engine.pca, p, propagate=engine.propagation) for p in pinned]
    coeffs = [synth.qp.coefficients(p[None])[0] for p in points]
    rgb = [synth.render(p[None])[0] for p in points[:2]]
    full = [to_uint8(image)[0] for image in rgb]
    jobs = {
        "propagate": lambda k: edited_geometry(engine.pca, pinned[k]),
        "propagate_drag": lambda k: edited_geometry(engine.pca, pinned[k], propagate=engine.propagation),
        "qp": lambda k: synth.qp.coefficients(points[k][None]),
        "composite_pipeline": lambda k: composite(synth.compositor, coeffs[k]),
        "composite_drag": lambda k: composite(previewer.compositor, coeffs[k]),
        "synth_pipeline": lambda k: synth.render(points[k][None]),
        "synth_drag": lambda k: previewer.render(points[k]),
        "uint8": lambda k: to_uint8(rgb[k % 2]),
        "jpeg": lambda k: encode(full[k % 2], mime="image/jpeg", jpeg_quality=engine.jpeg_quality),
        "png": lambda k: encode(full[k % 2], mime="image/png"),
    }
    times: dict[str, list[float]] = {name: [] for name in jobs}
    with torch.inference_mode():
        for k in range(repeats):  # the parts interleaved, so that a change of load hits them alike
            for name, job in jobs.items():
                start = time.thread_time()
                job(k)
                times[name].append((time.thread_time() - start) * 1e3)
    return {name: float(np.median(values)) for name, values in times.items()}


def save_screenshot(page, path: Path, *, max_bytes: int = 300_000) -> None:
    """A PNG of the editor after an edit (lower lip dragged down, a keyframe saved, subregions
    shown), downscaled until it is under ``max_bytes``."""
    page.click("#reset")
    page.evaluate("window.editor.idle()")
    page.click("#save-key")
    layout = page.evaluate("window.editor.layout()")
    x, y = page.evaluate("window.editor.geometry()")[layout["names"].index("mouth_outer_12")]
    box = page.locator("#overlay").bounding_box()
    page.mouse.move(box["x"] + x + 0.5, box["y"] + y + 0.5)
    page.mouse.down()
    for k in range(1, 21):
        page.mouse.move(box["x"] + x + 0.5, box["y"] + y + 0.5 + 1.5 * k)
    page.mouse.up()
    page.evaluate("window.editor.idle()")
    page.click("#save-key")
    page.check("#show-subregions")
    png = page.screenshot(full_page=True)
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    scale = 1.0
    while True:
        small = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else image
        ok, data = cv2.imencode(".png", small, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        if ok and (len(data) <= max_bytes or scale < 0.2):
            break
        scale *= 0.85
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data.tobytes())


if __name__ == "__main__":
    import json

    for r in run(argparse.Namespace(extra=sys.argv[1:], work=ROOT / ".cache" / "bench")):
        print(json.dumps(r))
