"""Synthesis benchmark: quality on held-out expressions, and speed at 600x800 with 15 examples.

Quality — the target pack's held-out expressions (captured expressions that are not examples),
each synthesized from its TRUE geometry, compared with its true image. The pack is the 600x800
demo target of ``make_fixtures.py --demo`` (rendered once under ``--work``; 28 held-out images)
unless ``--pack`` names another pack with a ``truth.npz``, or ``--combo`` asks for the 600x800
combinatorial pack (examples moving one facial region each, held-out expressions combining
regions: the paper's central claim; rows prefixed ``synth_combo_``, e.g.
``synth_combo_wrinkle_psnr_db`` and ``synth_combo_wrinkle_psnr_db_global``):

* ``synth_psnr_db``, ``synth_ssim``: PSNR / SSIM over the face (the layout's subregions rasterized
  on the true geometry);
* ``synth_wrinkle_psnr_db``: PSNR over the wrinkle areas (forehead, brow furrow, eye corners,
  nasolabial folds; defined from the layout points in :func:`wrinkle_mask`);

* ``synth_subregion_psnr_db_<subregion>``: PSNR over each layout subregion (rasterized on the true
  geometry), the squared error pooled over the held-out expressions
  (``lab.synthesis.metrics.pooled_psnr``: averaging per-image dB would let an expression that
  leaves a subregion exactly as in the neutral, 100+ dB under ``warp-only``, dominate the mean);

for the method (``full``), ``_warponly`` (traditional expression mapping: the neutral warped) and
``_global`` (one convex combination over the whole face, Pighin et al.); and, as bounds that see the
truth, ``_oracle`` / ``_oracleglobal`` (per subregion / over the whole face, the convex combination
of the aligned examples fitted to the true image: ``lab.synthesis.oracle``). A contact sheet
(truth | ours | warp-only | global) goes to ``<work>/synthesis/synthesis_sheet.png`` (the
README's ``docs/img/synthesis_sheet.png`` is a copy of it).

Speed — ``synth_fps``: frames/s of the whole runtime synthesis as the stage runs it
(``Synthesizer.render_half``: the chunk's QPs batched, then per frame compositing with small
coefficients skipped, warp, half-float outputs; no coefficient memo) at 600x800 with 15 examples on 2 threads; ``synth_fps_direct``: the
same with every example composited at every pixel (the paper's implementation), measured in the
same run; ``synth_speedup`` = their ratio; ``synth_cpu_ms``: CPU time (``time.process_time``, all
threads) per frame of the sparse path, least of the repeats; ``synth_fps_warponly`` /
``synth_cpu_ms_warponly``: the same for ``warp-only`` mode (the neutral warped, no QP, no
compositing), in the same run. The pack is resized to 600x800 (points scaled) when it
has another size; missing examples (fewer than 15) are taken from the held-out expressions.
``--device cuda`` (a GPU machine): the same rows on the GPU, named ``synth_fps_cuda``,
``synth_cpu_ms_cuda`` ..., each timed run ending with ``torch.cuda.synchronize()``.

    python scripts/bench.py synthesis --json [--pack fixtures/packs/target | --combo] [--frames 16] [--repeats 5]
                                         [--detail-power P] [--detail-sigma-px S] [--flow-max-px F] [--ridge-px T]

(the last four: the Sec. 15 remedies and the coefficient regularisation of :class:`Synthesizer`, its
defaults when absent).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from stages.actor_pack import ActorPack, Expression, load_pack  # noqa: E402
from stages.layout import Layout, subregion_mask  # noqa: E402
from stages.synthesis.build import build_synthesis_model  # noqa: E402
from lab.synthesis.metrics import masked_psnr, masked_ssim, pooled_psnr, subregion_errors  # noqa: E402
from lab.synthesis.oracle import texture_oracle  # noqa: E402
from lab.synthesis.align import refine_model  # noqa: E402
from stages.synthesis.synthesize import DETAIL_POWER, DETAIL_SIGMA_PX, RIDGE_PX, Synthesizer  # noqa: E402
from stages.synthesis.warp import warp_images  # noqa: E402

SPEED_SIZE = (600, 800)  # (W, H)
SPEED_EXAMPLES = 15
MODES = (("full", ""), ("warp-only", "_warponly"), ("global", "_global"))
ORACLES = (("full", "_oracle"), ("global", "_oracleglobal"))  # texture oracles (lab.synthesis.oracle)


def wrinkle_mask(layout: Layout, points: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """The wrinkle areas of one face, from its feature points (N, 2) px; (H, W) bool.

    * forehead: the polygon hairline_0..4 over the upper edges of both brows;
    * brow furrow: brow_l_7, brow_r_7, brow_r_0, nose_bridge_0, brow_l_0 (between the brows);
    * eye corners: a disc lateral of each outer eye corner (eye_*_6), centre half an eye width
      out, radius 0.6 eye width (crow's feet);
    * nasolabial folds: a band along nose_ala_*, nasolabial_*_0..2, a quarter of the mouth width
      wide, shifted a little laterally (the fold lies just outside the line).
    """
    W, H = size
    mask = np.zeros((H, W), np.uint8)
    P = lambda name: points[layout.index(name)]

    def poly(names: list[str]) -> None:
        cv2.fillPoly(mask, [np.round(np.array([P(n) for n in names]) * 16).astype(np.int32)], 1, cv2.LINE_8, 4)

    poly(
        [f"hairline_{k}" for k in range(5)]
        + ["brow_r_4", "brow_r_5", "brow_r_6", "brow_r_7", "brow_l_7", "brow_l_6", "brow_l_5", "brow_l_4"]
    )
    poly(["brow_l_7", "brow_r_7", "brow_r_0", "nose_bridge_0", "brow_l_0"])
    mouth_w = float(np.linalg.norm(P("mouth_outer_0") - P("mouth_outer_8")))
    for s, sx in (("l", -1.0), ("r", 1.0)):
        eye_w = float(np.linalg.norm(P(f"eye_{s}_0") - P(f"eye_{s}_6")))
        c = P(f"eye_{s}_6") + np.array([sx * 0.5 * eye_w, 0.0])
        cv2.circle(mask, tuple(int(v) for v in np.round(c)), int(round(0.6 * eye_w)), 1, -1)
        line = np.array([P(f"nose_ala_{s}")] + [P(f"nasolabial_{s}_{k}") for k in range(3)]) + np.array(
            [sx * 0.06 * mouth_w, 0.0]
        )
        cv2.polylines(mask, [np.round(line * 16).astype(np.int32)], False, 1, max(1, int(round(0.25 * mouth_w))), cv2.LINE_8, 4)
    return mask.astype(bool)


def face_mask(layout: Layout, points: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: pixels inside the layout's subregions drawn on ``points``."""
    return subregion_mask(layout, points, size) >= 0


def held_out(pack: ActorPack) -> list[Expression]:
    """The pack's held-out expressions that have an image, with their true geometry.

    Read from the fixture pack's ``truth.npz`` (docs/fixtures.md): ``heldout_index`` into
    ``captured_points``, ``heldout_image`` paths relative to the pack ('' = no image).
    """
    with np.load(pack.path / "truth.npz", allow_pickle=False) as truth:
        index, paths = truth["heldout_index"], truth["heldout_image"]
        points = truth["captured_points"]
    out = []
    for k, rel in zip(index, paths):
        if rel:
            image = cv2.cvtColor(cv2.imread(str(pack.path / str(rel)), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
            out.append(Expression(Path(str(rel)).stem, image, np.asarray(points[k], np.float64)))
    if not out:
        raise SystemExit(f"bench synthesis: {pack.path} has no held-out expression images (truth.npz)")
    return out


def to_tensor(image: np.ndarray) -> torch.Tensor:
    """(H, W, 3) uint8 -> (3, H, W) float64 in [0, 1]."""
    return torch.from_numpy(image).permute(2, 0, 1).double() / 255.0


def quality(
    pack: ActorPack, truths: list[Expression], sheet_path: Path, *, flow_max_px: float = 0.0, **synthesis: float
) -> list[dict]:
    """PSNR / SSIM per mode over held-out expressions; writes the contact sheet.

    ``flow_max_px``: the examples' alignment refined by optical flow bounded to this many px
    (:func:`lab.synthesis.align.refine_model`; 0: as built). ``synthesis``: keyword options of
    :class:`Synthesizer` (its defaults when absent).
    """
    model = build_synthesis_model(pack)
    synth = Synthesizer(refine_model(model, max_px=flow_max_px), **synthesis)
    size = pack.image_size
    methods = [(mode, suffix) for mode, suffix in MODES] + [(suffix, suffix) for _, suffix in ORACLES]
    scores = {key: {"psnr": [], "ssim": [], "wrinkle": [], "subregions": []} for key, _ in methods}
    names = [s.name for s in pack.layout.subregions]
    rows: list[np.ndarray] = []
    points = np.stack([t.points for t in truths])
    renders = {}
    for mode, _ in MODES:
        out = [synth.render(points[k : k + 8], mode=mode)[0] for k in range(0, len(points), 8)]
        renders[mode] = torch.cat(out).double()
    truth_std = torch.stack([warp_to_standard(synth, t) for t in truths])
    for mode, suffix in ORACLES:
        out = [
            synth.render(points[k : k + 8], mode=mode, coeffs=texture_oracle(model, truth_std[k : k + 8], mode=mode))[0]
            for k in range(0, len(points), 8)
        ]
        renders[suffix] = torch.cat(out).double()
    for k, truth in enumerate(truths):
        ref = to_tensor(truth.image)
        region = subregion_mask(pack.layout, truth.points, size)
        face = torch.from_numpy(region >= 0)
        wrinkles = torch.from_numpy(wrinkle_mask(pack.layout, truth.points, size)) & face
        for mode, _ in methods:
            img = renders[mode][k]
            scores[mode]["psnr"].append(masked_psnr(img, ref, face))
            scores[mode]["ssim"].append(masked_ssim(img, ref, face))
            scores[mode]["wrinkle"].append(masked_psnr(img, ref, wrinkles))
            scores[mode]["subregions"].append(subregion_errors(img, ref, region, names))
        if len(rows) < 4:
            row = [truth.image] + [(renders[m][k].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8) for m, _ in MODES]
            rows.append(np.concatenate(row, 1))
    ys, xs = np.nonzero(face_mask(pack.layout, truths[0].points, size))
    pad = 0.12 * (ys.max() - ys.min())
    y0, y1 = int(max(ys.min() - pad, 0)), int(min(ys.max() + pad, size[1]))
    x0, x1 = int(max(xs.min() - pad, 0)), int(min(xs.max() + pad, size[0]))
    W = size[0]
    sheet = np.concatenate([np.concatenate([r[y0:y1, c * W + x0 : c * W + x1] for c in range(4)], 1) for r in rows], 0)
    header = np.full((48, sheet.shape[1], 3), 255, np.uint8)
    for c, label in enumerate(("truth", "ours (full)", "warp-only", "global")):
        cv2.putText(header, label, (c * (x1 - x0) + 12, 34), cv2.FONT_HERSHEY_SIMPLEX, 1.0, (0, 0, 0), 2, cv2.LINE_AA)
    sheet = np.concatenate([header, sheet], 0)
    scale = min(1.0, 1800 / sheet.shape[1])
    sheet = cv2.resize(sheet, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    sheet_path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(sheet_path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    out = []
    for mode, suffix in methods:
        s = scores[mode]
        out += [
            {"bench": "synthesis", "metric": f"synth_psnr_db{suffix}", "value": float(np.mean(s["psnr"])), "unit": "dB"},
            {"bench": "synthesis", "metric": f"synth_ssim{suffix}", "value": float(np.mean(s["ssim"])), "unit": "1"},
            {
                "bench": "synthesis",
                "metric": f"synth_wrinkle_psnr_db{suffix}",
                "value": float(np.mean(s["wrinkle"])),
                "unit": "dB",
            },
        ]
        out += [
            {"bench": "synthesis", "metric": f"synth_subregion_psnr_db_{name}{suffix}", "value": value, "unit": "dB"}
            for name, value in pooled_psnr(s["subregions"]).items()
        ]
    out.append({"bench": "synthesis", "metric": "synth_heldout_count", "value": len(truths), "unit": "expressions"})
    return out


def warp_to_standard(synth: Synthesizer, expr: Expression) -> torch.Tensor:
    """An expression's image warped from its geometry to the standard geometry, (3, H, W) float32 in [0, 1]."""
    src = torch.from_numpy(np.concatenate([expr.points, synth.anchors]))[None]
    image = torch.from_numpy(expr.image).permute(2, 0, 1)[None].float() / 255.0
    return warp_images(image, src, synth.standard_points[None], synth.triangles)[0]


def resized(expr: Expression, size: tuple[int, int], from_size: tuple[int, int]) -> Expression:
    """An expression resized to ``size`` (W, H), points scaled (pixel-centre convention)."""
    if tuple(size) == tuple(from_size):
        return expr
    sx, sy = size[0] / from_size[0], size[1] / from_size[1]
    pts = (expr.points + 0.5) * [sx, sy] - 0.5
    return Expression(expr.name, cv2.resize(expr.image, size, interpolation=cv2.INTER_LINEAR), pts)


def speed_pack(pack: ActorPack, truths: list[Expression]) -> ActorPack:
    """The pack at 600x800 with exactly 15 examples (held-out expressions fill in)."""
    size = SPEED_SIZE
    r = lambda e: resized(e, size, pack.image_size)
    examples = [r(e) for e in (pack.examples + truths)[:SPEED_EXAMPLES]]
    while len(examples) < SPEED_EXAMPLES:
        examples.append(examples[len(examples) % len(pack.examples)])
    return ActorPack(
        path=pack.path,
        name=pack.name,
        layout=pack.layout,
        neutral=r(pack.neutral),
        standard=r(pack.standard),
        examples=examples,
        teeth_examples=[r(e) for e in pack.teeth_examples],
        captured_points=pack.captured_points,
        model3d=pack.model3d,
        intrinsics=pack.intrinsics,
        image_size=size,
    )


def speed(
    pack: ActorPack,
    truths: list[Expression],
    *,
    frames: int,
    chunk: int,
    repeats: int,
    device: str = "cpu",
    flow_max_px: float = 0.0,
    **synthesis: float,
) -> list[dict]:
    """synth_fps (sparse) and synth_fps_direct, interleaved runs, best of ``repeats`` each; on
    ``device`` ``cuda`` the rows are named ``synth_fps_cuda`` ... (each timed run waits for the GPU).

    The best run is the least disturbed by other processes; the 1-minute load average at the
    end is reported alongside (``synth_load_avg``) because the figures mean little on a busy
    machine.
    """
    big = speed_pack(pack, truths)
    model = refine_model(build_synthesis_model(big), max_px=flow_max_px)
    synth = Synthesizer(model, device=device, memo_frames=0, **synthesis)  # every QP solved
    sx, sy = SPEED_SIZE[0] / pack.image_size[0], SPEED_SIZE[1] / pack.image_size[1]
    geometry = (np.asarray(pack.captured_points, np.float64) + 0.5) * [sx, sy] - 0.5
    geometry = geometry[np.arange(frames) % len(geometry)]

    def run(variant: str) -> tuple[float, float]:
        t0, c0 = time.perf_counter(), time.process_time()
        for k in range(0, frames, chunk):
            synth.render_half(
                geometry[k : k + chunk], direct=variant == "direct", mode="warp-only" if variant == "warponly" else "full"
            )
        if device == "cuda":
            torch.cuda.synchronize()
        return frames / (time.perf_counter() - t0), (time.process_time() - c0) / frames * 1e3

    synth.render_half(geometry[:chunk])  # warm-up
    variants = ("full", "direct", "warponly")
    best, cpu_ms = dict.fromkeys(variants, 0.0), dict.fromkeys(variants, float("inf"))
    for _ in range(repeats):
        for variant in variants:
            fps, ms = run(variant)
            best[variant], cpu_ms[variant] = max(best[variant], fps), min(cpu_ms[variant], ms)
    suffix = "_cuda" if device == "cuda" else ""
    rows = [
        {"bench": "synthesis", "metric": "synth_fps", "value": best["full"], "unit": "frames/s"},
        {"bench": "synthesis", "metric": "synth_cpu_ms", "value": cpu_ms["full"], "unit": "ms/frame"},
        {"bench": "synthesis", "metric": "synth_fps_direct", "value": best["direct"], "unit": "frames/s"},
        {"bench": "synthesis", "metric": "synth_speedup", "value": best["full"] / best["direct"], "unit": "x"},
        {"bench": "synthesis", "metric": "synth_fps_warponly", "value": best["warponly"], "unit": "frames/s"},
        {"bench": "synthesis", "metric": "synth_cpu_ms_warponly", "value": cpu_ms["warponly"], "unit": "ms/frame"},
        {"bench": "synthesis", "metric": "synth_threads", "value": torch.get_num_threads(), "unit": "threads"},
        {"bench": "synthesis", "metric": "synth_load_avg", "value": os.getloadavg()[0], "unit": "processes"},
    ]
    for row in rows:
        row["metric"] += suffix
    return rows


def run(args: argparse.Namespace) -> list[dict]:
    parser = argparse.ArgumentParser(prog="bench.py synthesis")
    parser.add_argument(
        "--pack",
        type=Path,
        default=None,
        help="target actor pack with truth.npz (default: the 600x800 demo target, generated under --work)",
    )
    parser.add_argument(
        "--combo", action="store_true", help="the 600x800 combinatorial pack (generated under --work); rows synth_combo_*"
    )
    parser.add_argument("--frames", type=int, default=16, help="frames timed per speed run")
    parser.add_argument("--repeats", type=int, default=5, help="speed runs per variant (the best counts)")
    parser.add_argument("--chunk", type=int, default=8, help="frames per render call")
    parser.add_argument("--only", choices=("all", "quality", "speed"), default="all", help="run one half of the benchmark")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (the target: 2 CPU cores)")
    parser.add_argument(
        "--sheet", type=Path, default=None, help="contact sheet PNG (default: <work>/synthesis/synthesis_sheet.png)"
    )
    parser.add_argument("--detail-power", type=float, default=DETAIL_POWER, help="band-pass blending power (1: plain eq. 6)")
    parser.add_argument("--detail-sigma-px", type=float, default=DETAIL_SIGMA_PX, help="band-pass split, Gaussian sigma, px")
    parser.add_argument("--flow-max-px", type=float, default=0.0, help="optical-flow refinement bound, px (0: off)")
    parser.add_argument(
        "--ridge-px", type=float, default=RIDGE_PX, help="coefficient regularisation of the QPs, px (0: plain eq. 2)"
    )
    parser.add_argument(
        "--device", default="cpu", choices=("cpu", "cuda"), help="speed rows on this device (cuda: synth_fps_cuda ...)"
    )
    opts = parser.parse_args(getattr(args, "extra", []))
    if opts.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: CUDA is not available on this machine")
    opts.sheet = opts.sheet or Path(args.work) / "synthesis" / "synthesis_sheet.png"
    torch.set_num_threads(opts.threads)
    cv2.setNumThreads(opts.threads)
    if opts.combo and opts.pack is not None:
        parser.error("--combo and --pack name two packs: give one")
    pack_dir = opts.pack or demo_pack(Path(args.work), part="pack:combo" if opts.combo else "pack:target")
    pack = load_pack(pack_dir)
    truths = held_out(pack)
    remedies = {
        "detail_power": opts.detail_power,
        "detail_sigma_px": opts.detail_sigma_px,
        "flow_max_px": opts.flow_max_px,
        "ridge_px": opts.ridge_px,
    }
    rows = quality(pack, truths, opts.sheet, **remedies) if opts.only in ("all", "quality") else []
    if opts.only in ("all", "speed"):
        rows += speed(pack, truths, frames=opts.frames, chunk=opts.chunk, repeats=opts.repeats, device=opts.device, **remedies)
    if opts.combo:
        for row in rows:
            row["metric"] = row["metric"].replace("synth_", "synth_combo_", 1)
    return rows


def demo_pack(work: Path, *, part: str = "pack:target") -> Path:
    """A paper-sized (600x800) pack of ``make_fixtures.py --demo``: the target (``pack:target``)
    or the combinatorial pack (``pack:combo``), generated once under ``work`` (that part only,
    the same identity and seed as ``make_fixtures.py --demo``)."""
    folder = work / "synthesis_demo" / "packs" / part.split(":")[1]
    if not (folder / "pack.yaml").is_file():
        from scripts.make_fixtures import DEMO, make_part

        make_part(work / "synthesis_demo", part, seed=1, spec=DEMO)
    return folder


if __name__ == "__main__":
    import json

    for row in run(argparse.Namespace(extra=sys.argv[1:])):
        print(json.dumps(row))
