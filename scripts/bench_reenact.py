"""Self-reenactment on real faces, the protocol of the paper's Fig. 10 (`python scripts/bench.py reenact`).

    python scripts/bench.py reenact [--json] [--work DIR] [--clip PATH ...] [--build-fraction 0.6]
                                    [--stride 1] [--sheet PATH] [--pose-deg DEG]
                                    [--detail-power P] [--detail-sigma-px S] [--flow-max-px F] [--ridge-px T]

Per clip (``--clip``, repeatable; default every ``*.mp4`` of ``../shared/dev-clips/``):

1. the landmark stages (``landmarks.mediapipe``, ``landmarks.layout``) on every frame;
2. an actor pack from the first ``--build-fraction`` of the frames with the pack stages
   (``pack.filter``, ``pack.select``, ``pack.write``, defaults but ``--pose-deg``), written to
   ``<work>/reenact/<stem>/pack``;
3. every ``--stride``-th frame of the rest with a face: its own layout points are aligned into the
   pack's frame by the least-squares similarity of the stable points (eye corners, nose tip and
   base) onto the pack neutral's, the frame itself by the same similarity; the synthesis model of
   the pack renders that geometry (no tracking, no expression mapping: the geometry is the
   frame's own) and the result is compared with the aligned real frame over the face (the
   layout's subregions rasterized on the frame's aligned points).

Methods: ``full`` (the paper's per-subregion synthesis), ``warponly`` (the neutral warped to the
geometry), ``global`` (one convex combination over the face, Pighin et al.), ``nearest`` (the
example nearest in geometry, warped), and two bounds that see the truth: ``oracle`` (per
subregion, the convex combination of the aligned examples fitted to the true frame, in the standard
geometry: ``lab.synthesis.oracle``; the best any choice of per-subregion coefficients can do)
and ``oracleglobal`` (one such fit over the whole face: the best of a global combination); and
``footage`` / ``footageglobal``: coefficients learned from the build frames the pack passed
(``lab.synthesis.footage``: per subregion / over the whole face, the mean of the oracle
coefficients of the k build frames nearest in geometry, k by blocked cross-validation on the build
frames; eq. 2 for the teeth). Rows
per clip (suffix ``_<clip stem>``), the method as a suffix of the metric (none for ``full``):
``reenact_psnr_db`` and ``reenact_ssim`` over the face, ``reenact_wrinkle_psnr_db`` over the forehead, glabella, eye zones (crow's feet) and cheeks
(nasolabial folds), each the mean over the test frames; ``reenact_subregion_psnr_db_<subregion>``
over each layout subregion on the frame's points, the PSNR of the squared error pooled over the
test frames (``lab.synthesis.metrics.pooled_psnr``). Also ``reenact_test_frames``,
``reenact_examples``, ``reenact_coverage_px`` (the examples' k-center radius) and
``reenact_rejected_<cause>`` (build frames ``pack.filter`` rejected, per cause),
``reenact_footage_k`` / ``reenact_footage_k_global`` (the cross-validated k) and
``reenact_margin_footage_db`` (footage minus footageglobal face PSNR). Over the clips:
``reenact_margin_warponly_db_min`` and ``reenact_margin_global_db_min`` (full minus baseline face
PSNR, the smallest over the clips) and ``reenact_margin_footage_db_min``. ``--sheet PATH`` writes a contact sheet (truth | full |
warp-only | global at 3 test frames per clip).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any, Iterator

import numpy as np

REPO = Path(__file__).resolve().parent.parent
DEV_CLIPS = REPO.parent / "shared" / "dev-clips"
BENCH = "reenact"
METHODS = {
    "full": "",
    "warponly": "_warponly",
    "global": "_global",
    "nearest": "_nearest",
    "oracle": "_oracle",
    "oracleglobal": "_oracleglobal",
    "footage": "_footage",
    "footageglobal": "_footageglobal",
}
WRINKLE_SUBREGIONS = ("forehead", "glabella", "eyezone_l", "eyezone_r", "cheek_l", "cheek_r")
BATCH = 8
SHEET_FRAMES = 3


def row(metric: str, value: float, unit: str) -> dict[str, Any]:
    return {"bench": BENCH, "metric": metric, "value": float(value), "unit": unit}


class Frames:
    """Decoded frames ``(T, H, W, 3)`` uint8 as a :class:`runner.stage.FrameStream`."""

    def __init__(self, frames: np.ndarray, fps: float) -> None:
        from runner.stage import StreamInfo

        self.frames = frames
        self.info = StreamInfo(frames=len(frames), fps=fps, width=frames.shape[2], height=frames.shape[1])

    def read(self, start: int, stop: int) -> np.ndarray:
        return self.frames[np.clip(np.arange(start, stop), 0, len(self.frames) - 1)]

    def chunks(self) -> Iterator[tuple[int, np.ndarray]]:
        for start in range(0, len(self.frames), 16):
            yield start, self.frames[start : start + 16]


def decode(clip: Path) -> Frames:
    import av

    with av.open(str(clip)) as container:
        stream = container.streams.video[0]
        fps = float(stream.average_rate or 25)
        frames = np.stack([f.to_ndarray(format="rgb24") for f in container.decode(stream)])
    return Frames(frames, fps)


def head(bundle: dict[str, np.ndarray], frames: int, total: int) -> dict[str, np.ndarray]:
    """The first ``frames`` frames of a per-frame bundle (numeric arrays whose first axis is
    ``total``; names and scalars pass whole)."""
    return {
        k: (v[:frames] if np.ndim(v) and len(v) == total and np.asarray(v).dtype.kind != "U" else v) for k, v in bundle.items()
    }


def build_pack(
    clip: Frames, work: Path, build: int, select: dict[str, Any]
) -> tuple[Path, dict[str, np.ndarray], dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Landmarks of the whole clip and a pack from its first ``build`` frames (``select``: parameters
    of ``pack.select``); returns the pack folder, the ``points`` bundle (whole clip), the
    ``pack_selection`` bundle and the ``frame_filter`` bundle (rejections per cause)."""
    from runner.stage import Context
    from stages.landmarks.stage import FaceLandmarks, LayoutPoints
    from stages.packbuild.stage import PackFilter, PackSelect, PackWrite

    ctx = Context(device="cpu", files_dir=lambda port: work / port, log=logging.getLogger("bench.reenact"))
    marks = FaceLandmarks().run({"frames": clip}, {}, ctx)["landmarks"]
    points = LayoutPoints().run({"landmarks": marks}, {}, ctx)["points"]
    T = clip.info.frames
    part = {
        "frames": Frames(clip.frames[:build], clip.info.fps),
        "landmarks": head(marks, build, T),
        "points": head(points, build, T),
    }
    part["filter"] = PackFilter().run(part, {}, ctx)["filter"]
    selection = PackSelect().run(part, select, ctx)["selection"]
    if (work / "pack").exists():
        import shutil

        shutil.rmtree(work / "pack")
    PackWrite().run({**part, "selection": selection}, {}, ctx)
    return work / "pack", points, selection, part["filter"]


def evaluate(
    clip: Frames,
    points: dict[str, np.ndarray],
    pack_dir: Path,
    test: np.ndarray,
    footage: np.ndarray,
    *,
    flow_max_px: float = 0.0,
    **synthesis: float,
) -> tuple[dict[str, dict[str, list]], list, dict[str, int]]:
    """Per method, the face PSNR, SSIM, wrinkle PSNR and subregion errors of every test frame;
    sheet tiles; the footage coefficients' cross-validated k per mode. ``footage``: the build
    frames the footage coefficients learn from (time order). ``flow_max_px``: the synthesized
    examples' alignment refined by optical flow bounded to this many px
    (:func:`lab.synthesis.align.refine_model`; 0: as built). ``synthesis``: keyword options of
    the ``Synthesizer`` (its defaults when absent)."""
    import torch
    from stages.actor_pack import load_pack
    from stages.geometry.compensate import apply_similarity, fit_similarity
    from stages.layout import subregion_mask
    from stages.packbuild.selection import stable_columns
    from stages.packbuild.writing import align_image
    from lab.synthesis.align import refine_model
    from stages.synthesis.build import build_synthesis_model
    from lab.synthesis.footage import FootageCoefficients
    from lab.synthesis.metrics import masked_psnr, masked_ssim, subregion_errors
    from lab.synthesis.oracle import texture_oracle
    from stages.synthesis.synthesize import Synthesizer
    from stages.synthesis.warp import warp_images

    pack = load_pack(pack_dir)
    layout, size = pack.layout, pack.image_size
    model = build_synthesis_model(pack)
    synth = Synthesizer(refine_model(model, max_px=flow_max_px), **synthesis)
    columns = stable_columns(layout)
    wrinkle = [k for k, s in enumerate(layout.subregions) if s.name in WRINKLE_SUBREGIONS]
    anchors = np.asarray(model["anchors"])
    example_points = np.stack([e.points for e in pack.examples])
    example_images = torch.from_numpy(np.stack([e.image for e in pack.examples])).permute(0, 3, 1, 2).float() / 255.0
    names = [s.name for s in layout.subregions]
    scores: dict[str, dict[str, list]] = {m: {"psnr": [], "ssim": [], "wrinkle": [], "subregions": []} for m in METHODS}
    tiles = []
    sheet_at = set(test[np.linspace(0, len(test) - 1, SHEET_FRAMES).round().astype(int)].tolist())
    xy = np.asarray(points["xy"], np.float64)

    def aligned(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, torch.Tensor]:
        """The frames' points and images aligned into the pack's frame, those points with the
        anchors, and the images warped to the standard geometry: ``(B, N, 2)``, ``(B, H, W, 3)``
        uint8, ``(B, N + A, 2)``, ``(B, 3, H, W)`` float."""
        params = [fit_similarity(xy[t, columns], pack.neutral.points[columns]) for t in frames]
        geometry = np.stack([apply_similarity(p, xy[t]) for p, t in zip(params, frames)])
        truth = np.stack([align_image(clip.frames[t], p, size)[0] for p, t in zip(params, frames)])
        dst = np.concatenate([geometry, np.broadcast_to(anchors, (len(frames),) + anchors.shape)], 1)
        images = torch.from_numpy(truth).permute(0, 3, 1, 2).float() / 255.0
        standard = warp_images(
            images, torch.from_numpy(dst), synth.standard_points[None].expand(len(frames), -1, -1), model["triangles"]
        )
        return geometry, truth, dst, standard

    learned = [aligned(footage[s : s + BATCH]) for s in range(0, len(footage), BATCH)]
    footage_qp = FootageCoefficients(
        model, np.concatenate([g for g, _, _, _ in learned]), torch.cat([st for _, _, _, st in learned])
    )
    del learned
    for start in range(0, len(test), BATCH):
        frames = test[start : start + BATCH]
        geometry, truth, dst, standard = aligned(frames)
        out = {m: synth.render(geometry, mode=m.replace("warponly", "warp-only"))[0] for m in ("full", "warponly", "global")}
        for m, mode in (("oracle", "full"), ("oracleglobal", "global")):
            out[m] = synth.render(geometry, mode=mode, coeffs=texture_oracle(model, standard, mode=mode))[0]
        for m, mode in (("footage", "full"), ("footageglobal", "global")):
            out[m] = synth.render(geometry, mode=mode, coeffs=footage_qp.coefficients(geometry, mode=mode))[0]
        nearest = np.argmin(np.sqrt(((geometry[:, None] - example_points[None]) ** 2).sum(-1).mean(-1)), axis=1)
        src = np.concatenate([example_points[nearest], np.broadcast_to(anchors, (len(frames),) + anchors.shape)], 1)
        out["nearest"] = warp_images(
            example_images[nearest], torch.from_numpy(src), torch.from_numpy(dst), model["triangles"]
        ).clamp(0, 1)
        for k, t in enumerate(frames):
            region = subregion_mask(layout, geometry[k], size)
            face, wr = torch.from_numpy(region >= 0), torch.from_numpy(np.isin(region, wrinkle))
            real = torch.from_numpy(truth[k]).permute(2, 0, 1).float() / 255.0
            for m in METHODS:
                img = out[m][k].float()
                scores[m]["psnr"].append(masked_psnr(img, real, face))
                scores[m]["ssim"].append(masked_ssim(img, real, face))
                scores[m]["wrinkle"].append(masked_psnr(img, real, wr))
                scores[m]["subregions"].append(subregion_errors(img, real, region, names))
            if int(t) in sheet_at:
                as_u8 = lambda x: (x.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
                tiles += [
                    (f"truth {t}", truth[k]),
                    ("full", as_u8(out["full"][k])),
                    ("warp-only", as_u8(out["warponly"][k])),
                    ("global", as_u8(out["global"][k])),
                ]
    return scores, tiles, footage_qp.k


def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(prog="bench.py reenact")
    parser.add_argument("--clip", type=Path, action="append", help="a real clip (repeatable)")
    parser.add_argument("--build-fraction", type=float, default=0.6, help="share of the frames the pack is built from")
    parser.add_argument("--stride", type=int, default=1, help="evaluate every n-th test frame")
    parser.add_argument("--sheet", type=Path, help="write a contact sheet PNG (truth | full | warp-only | global)")
    parser.add_argument("--pose-deg", type=float, help="pack.select's pose_deg (default: the stage's)")
    parser.add_argument("--detail-power", type=float, help="band-pass blending power (default: the Synthesizer's)")
    parser.add_argument("--detail-sigma-px", type=float, help="band-pass split, Gaussian sigma, px (default: the Synthesizer's)")
    parser.add_argument("--flow-max-px", type=float, help="optical-flow refinement bound, px, 0: off (default: 0)")
    parser.add_argument(
        "--ridge-px", type=float, help="coefficient regularisation of the QPs, px, 0: plain eq. 2 (default: the Synthesizer's)"
    )
    extra = parser.parse_args(args.extra)
    clips = extra.clip or sorted(DEV_CLIPS.glob("*.mp4"))
    if not clips:
        raise SystemExit(f"bench reenact: no clip given and none in {DEV_CLIPS}")
    from stages.packbuild.writing import contact_sheet, write_png
    from lab.synthesis.metrics import pooled_psnr

    rows: list[dict[str, Any]] = []
    margins: dict[str, list[float]] = {"warponly": [], "global": []}
    footage_margins: list[float] = []
    tiles = []
    for clip_path in clips:
        stem = clip_path.stem
        work = Path(args.work) / "reenact" / stem
        work.mkdir(parents=True, exist_ok=True)
        clip = decode(clip_path)
        build = int(round(extra.build_fraction * clip.info.frames))
        select = {} if extra.pose_deg is None else {"pose_deg": extra.pose_deg}
        pack_dir, points, selection, filt = build_pack(clip, work, build, select)
        print(f"bench reenact: {stem}: pack built from frames 0-{build - 1} in {pack_dir}", file=sys.stderr, flush=True)
        valid = np.asarray(points["valid"], bool).all(axis=1)
        test = np.flatnonzero(valid[build:])[:: max(1, extra.stride)] + build
        remedies = {
            k: getattr(extra, k)
            for k in ("detail_power", "detail_sigma_px", "flow_max_px", "ridge_px")
            if getattr(extra, k) is not None
        }
        footage = np.flatnonzero(np.asarray(filt["keep"], bool))
        scores, clip_tiles, footage_k = evaluate(clip, points, pack_dir, test, footage, **remedies)
        tiles += clip_tiles
        for method, suffix in METHODS.items():
            rows.append(row(f"reenact_psnr_db{suffix}_{stem}", np.mean(scores[method]["psnr"]), "dB"))
            rows.append(row(f"reenact_ssim{suffix}_{stem}", np.mean(scores[method]["ssim"]), "1"))
            rows.append(row(f"reenact_wrinkle_psnr_db{suffix}_{stem}", np.mean(scores[method]["wrinkle"]), "dB"))
            for name, value in pooled_psnr(scores[method]["subregions"]).items():
                rows.append(row(f"reenact_subregion_psnr_db_{name}{suffix}_{stem}", value, "dB"))
        full = np.mean(scores["full"]["psnr"])
        for baseline in margins:
            margins[baseline].append(full - np.mean(scores[baseline]["psnr"]))
            rows.append(row(f"reenact_margin_{baseline}_db_{stem}", margins[baseline][-1], "dB"))
        footage_margins.append(np.mean(scores["footage"]["psnr"]) - np.mean(scores["footageglobal"]["psnr"]))
        rows.append(row(f"reenact_margin_footage_db_{stem}", footage_margins[-1], "dB"))
        rows.append(row(f"reenact_footage_k_{stem}", footage_k["full"], "frames"))
        rows.append(row(f"reenact_footage_k_global_{stem}", footage_k["global"], "frames"))
        rows.append(row(f"reenact_test_frames_{stem}", len(test), "frames"))
        rows.append(row(f"reenact_examples_{stem}", len(selection["examples"]), "examples"))
        rows.append(row(f"reenact_coverage_px_{stem}", float(selection["example_radius_px"]), "px"))
        for cause, count in zip(filt["cause_names"], filt["counts"]):
            rows.append(row(f"reenact_rejected_{cause}_{stem}", count, "frames"))
    for baseline, values in margins.items():
        rows.append(row(f"reenact_margin_{baseline}_db_min", min(values), "dB"))
    rows.append(row("reenact_margin_footage_db_min", min(footage_margins), "dB"))
    if extra.sheet is not None:
        extra.sheet.parent.mkdir(parents=True, exist_ok=True)
        write_png(extra.sheet, contact_sheet(tiles, columns=4, thumb_height=200))
    return rows
