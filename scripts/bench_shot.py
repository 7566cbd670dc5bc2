"""A usable shot on a real target (`python scripts/bench.py shot`).

    python scripts/bench.py shot [--json] [--work DIR] [--clip PATH ...] [--target-clip PATH ...]
                                 [--no-turn] [--no-pose] [--no-invented] [--no-speed] [--sheets]
                                 [--speed-clip PATH] [--wide-clip PATH] [--wide-width 1024]

Five parts, each run by the runner as a user runs it:

**Head turns against truth** (``--no-turn`` skips). The real-texture generator
(``lab/realface``, with its backdrop: the head of face, hair, ears and neck in front of a static
background) renders the target twice: a frontal clip with expressions, made into a pack by
``pack_build.yaml``; and a performance of the same person at known poses (neutral expression,
yaw up to +-30 deg, pitch up to +-15 deg, roll up to +-10 deg, from a frontal start). The
performance is mapped onto the pack (self-reenactment: the truth is the performance itself, cut
into the pack's frame by the similarity ``pack.yaml`` records for the neutral) by
``pipeline_3d.yaml`` (the 2D result with the depth-aware head turn, and the 3D render) and by
``pipeline.yaml`` with ``synthesize.head_motion=similarity`` (the paper's 2D similarity), both with
the rest frame as the reference, the target's rest pose taken as the performer's
(``head3d.absolute=false``: it is the same face) and ``compensate.close_lips=false`` (the portrait's
rest face shows its teeth). Over the
frames turned more than 10 deg (true yaw or pitch), PSNR (dB, sRGB) and SSIM of each output's
plate (EXR ``plate.R/G/B``) against the truth, over the whole frame and over the face (the face
oval of the true landmarks): ``shot_turn_psnr_db`` / ``_2dsim`` and ``shot_turn3d_psnr_db``,
``..._face``, ``shot_turn_ssim`` ...; ``shot_turn_gain_db`` (depth warp minus similarity) and
``shot_turn3d_gap_db`` (3D minus 2D); ``shot_turn_frames``. The filled pixels (``filled.A`` > 0.5)
of the 2D result's turned frames, filled again from its real pixels by the pipeline's push-pull
and by ``cv2.inpaint`` (Telea), against the truth: ``shot_fill_psnr_db_pushpull`` / ``_telea``, and
their CPU ms per frame ``shot_fill_ms_*`` (``shot_fill_frames``: the frames with any). A sheet (truth | 2D | 2D similarity |
3D at the largest yaw and pitch) goes to ``<work>/shot/turn/sheet.png``.

**Head pose slopes** (``--no-pose`` skips). How large the head rotation the pipeline applies
(``compensate.pose``, ``ypr_deg``) is against the rotation the performer made, per axis: the slope
of a least-squares line of ours against the reference over the frames with a face (1: every turn as
large as made). Against exact truth: a real-texture clip of the astronaut's head (no expression) at
known poses (:func:`turn_motion` continued by sweeps of yaw +-35, pitch +-20 and roll +-25 deg),
relative to frame 0, ``shot_pose_slope_{yaw,pitch,roll}``. Against MediaPipe's facial
transformation matrix (relative to the same head frame) on every ``--clip``:
``shot_pose_slope_<axis>_mp_<clip>``, and ``shot_pose_slope_<axis>_mp`` the one farthest from 1
over the clips. The same rows with ``_points`` appended measure ``compensate.pose_rotation=points``
(the weak-perspective fit of the rigid points) in the same run. Runs ``pipeline.yaml`` up to
``compensate`` through the runner's Python API (the same stages and cache as the CLI).

**Invented pixels** (``--no-invented`` skips). Packs from ``--target-clip`` (default ``LP_d18`` and
``WDA_AlexandriaOcasioCortez_000``) by ``pack_build.yaml``; every ``--clip`` (default every dev
clip) mapped onto each by ``pipeline.yaml``. Independently of the pipeline's own mattes, the
benchmark makes an *indicator pack*: each image replaced by where it comes from inside its clip's
frame (white) or beyond it (black), from the cut's similarity and the footage size ``pack.yaml``
records (the writer's mattes are not read); it is synthesized frame by frame with the run's
geometry (``data.npz``) and head motion (the EXR headers), positions beyond the pack image reading
black. Per pixel, the part that comes from beyond a real source image (``1 - indicator``) and is not
marked (``filled.A``): ``max(0, 1 - indicator - filled)``; ``shot_invented_px_frac_<clip>`` is its
mean over the output pixels and frames (both packs), so an edge-replicated streak counts whole
and a pixel on the footage's edge marked as it straddles it counts nothing;
``shot_invented_px_frac_max`` over the clips; ``shot_filled_px_frac_<clip>`` the mean of
``filled.A`` (what the run filled and marked).

**Speed and size** (``--no-speed`` skips). ``pipeline.yaml`` end to end (landmarks, every output)
from an empty cache, ``--speed-clip`` (default ``LP_d3``) onto the 384x512 ``LP_d18`` pack:
``shot_fps_384``; onto a pack ``--wide-width`` px wide built from ``--wide-clip`` (default
``LP_d13``, 720x1280): ``shot_fps_1024``; each with ``shot_peak_mb_<size>`` (the largest resident
set of the run's processes), ``shot_cache_mb_per_100_frames_<size>`` and the profile
``shot_ms_per_frame_<stage>_<size>`` and the baseline measured in the same run,
``shot_fps_<size>_warponly`` (``synthesize.mode=warp-only``, ``head_motion=similarity``,
``exr.layers=face``: traditional expression mapping) and ``shot_fps_<size>_ratio_warponly`` (the
full run's frames/s over it); the profile is each stage's CPU time per frame, from ``--log-json``: the
runner's CPU clock of the stage's own work, which leaves out the threads of a library's pool, e.g.
MediaPipe's and the EXR writer's; stages run on two cores at once).

**Contact sheets** (``--sheets``): performer | 2D | 3D at the largest yaw, pitch and roll of each
``--clip`` onto the first pack (``pipeline_3d.yaml``), ``<work>/shot/sheets/<clip>.png``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent
DEV_CLIPS = REPO.parent / "shared" / "dev-clips"
BENCH = "shot"
TURNED_DEG = 10.0
TARGET_CLIPS = ("LP_d18", "WDA_AlexandriaOcasioCortez_000")


def row(metric: str, value: float, unit: str) -> dict[str, Any]:
    return {"bench": BENCH, "metric": metric, "value": float(value), "unit": unit}


def runner(pipeline: str, clip: Path, out: Path, cache: Path, *extra: str) -> tuple[float, list[dict[str, Any]]]:
    """``runner run PIPELINE --in CLIP --out OUT --cache-dir CACHE ...``; the wall time (s) and the
    ``--log-json`` events (a child process's own events unwrapped). SystemExit on failure."""
    log = out.parent / f"{out.name}.log.jsonl"
    out.parent.mkdir(parents=True, exist_ok=True)
    log.unlink(missing_ok=True)
    command = [
        sys.executable,
        "-c",
        "from runner.cli import main; main()",
        "run",
        str(REPO / pipeline),
        "--in",
        str(clip),
        "--out",
        str(out),
        "--cache-dir",
        str(cache),
        "--log-json",
        str(log),
        *extra,
    ]
    start = time.perf_counter()
    result = subprocess.run(command, cwd=REPO, env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True, text=True)
    elapsed = time.perf_counter() - start
    if result.returncode != 0:
        raise SystemExit(f"{pipeline} failed on {clip} ({result.returncode}): {result.stderr.strip()[-2000:]}")
    events = [json.loads(line) for line in log.read_text().splitlines()]
    return elapsed, [e["child"] if e.get("event") == "child" else e for e in events]


def build_pack(clip: Path, work: Path, *extra: str) -> Path:
    """``pack_build.yaml`` on ``clip`` into ``work``; the pack folder."""
    runner("pack_build.yaml", clip, work / "out", work / "cache", *extra)
    return work / "out" / "pack"


def read_exr(path: Path) -> tuple[dict[str, np.ndarray], Any]:
    """An EXR's channels by name (float32 planes) and its OpenImageIO spec."""
    import OpenImageIO as oiio

    image = oiio.ImageInput.open(str(path))
    if image is None:
        raise SystemExit(f"cannot open {path}: {oiio.geterror()}")
    spec = image.spec()
    pixels = image.read_image("float")
    image.close()
    return {name: pixels[..., k] for k, name in enumerate(spec.channelnames)}, spec


def plate_srgb(channels: dict[str, np.ndarray]) -> np.ndarray:
    """``(H, W, 3)`` float sRGB in [0, 1] of an EXR's ``plate`` layer (the whole frame)."""
    from stages.color import linear_to_srgb

    linear = np.stack([channels[f"plate.{c}"] for c in "RGB"], -1)
    return np.clip(linear_to_srgb(np.clip(linear, 0.0, None)), 0.0, 1.0)


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR (dB) of images in [0, 1], over ``mask`` (H, W) when given."""
    err = (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2
    mse = err.mean() if mask is None else err[mask].mean()
    return float(10.0 * np.log10(1.0 / max(mse, 1e-12)))


def ssim(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """SSIM of RGB images in [0, 1] (skimage, Gaussian window), its map averaged over ``mask``."""
    from skimage.metrics import structural_similarity

    _, full = structural_similarity(a, b, channel_axis=2, data_range=1.0, gaussian_weights=True, full=True)
    full = full.mean(-1)
    return float(full.mean() if mask is None else full[mask].mean())


# -- head turns against truth ---------------------------------------------------------------------


def turn_motion(frames_still: int = 8, frames_sweep: int = 32) -> np.ndarray:
    """``(T, 3)`` yaw, pitch, roll (deg) of the performance: still and frontal, then smooth sweeps
    of yaw (+-30), pitch (+-15), yaw with pitch (+-20, +-10), roll (+-10)."""
    s = np.sin(2 * np.pi * np.arange(frames_sweep) / frames_sweep)
    parts = [
        np.zeros((frames_still, 3)),
        np.column_stack([30 * s, 0 * s, 0 * s]),
        np.column_stack([0 * s, 15 * s, 0 * s]),
        np.column_stack([20 * s, 10 * np.sin(4 * np.pi * np.arange(frames_sweep) / frames_sweep), 0 * s]),
        np.column_stack([0 * s, 0 * s, 10 * s]),
    ]
    return np.concatenate(parts)


def target_expressions(frames: int = 60) -> np.ndarray:
    """``(T, 3)`` expression parameters (mouth open, brow raise, smile) of the pack's footage: a
    neutral start, then each expression and mixes rising and falling."""
    t = np.arange(frames)
    bump = lambda start, length: np.clip(np.sin(np.pi * (t - start) / length), 0, None) * ((t >= start) & (t < start + length))
    return np.column_stack(
        [bump(6, 16) + bump(40, 14), bump(20, 12) + 0.6 * bump(40, 14), bump(30, 14) + 0.5 * bump(46, 10)]
    ).clip(0, 1)


def render_clip(face, path: Path, params: np.ndarray, angles: np.ndarray, fps: int = 25) -> dict[str, np.ndarray]:
    """Render a real-texture clip (H.264, crf 12) and return its truth: frames, landmark points, coverage."""
    from lab.realface.clip import render_state
    from stages.video import VideoWriter

    size = face.mesh.size
    truth = {"frames": [], "points": [], "coverage": []}
    with VideoWriter(path, fps=fps, width=size, height=size, codec="h264", crf=12) as writer:
        for p, a in zip(params, angles):
            frame, *_ = render_state(face, p, a, np.zeros(3))
            writer.write(frame.image[None])
            truth["frames"].append(frame.image)
            truth["points"].append(frame.points)
            truth["coverage"].append(frame.coverage)
    return {k: np.stack(v) for k, v in truth.items()}


def face_region(points: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``(H, W) bool``: inside the face oval of MediaPipe landmarks ``points (478, 2)``."""
    import cv2
    from lab.realface.landmarks import FACE_OVAL

    mask = np.zeros(shape, np.uint8)
    cv2.fillPoly(mask, [np.round(points[list(FACE_OVAL)]).astype(np.int32)], 1)
    return mask.astype(bool)


def turn_rows(work: Path) -> list[dict[str, Any]]:
    """The head-turn part (module docstring)."""
    import cv2
    import yaml
    from lab.realface.clip import fit_real_face
    from stages.packbuild.writing import contact_sheet, write_png

    work.mkdir(parents=True, exist_ok=True)
    face = fit_real_face(512, backdrop=True)
    expressions = target_expressions()
    render_clip(face, work / "target.mp4", expressions, np.zeros((len(expressions), 3)))
    pack = build_pack(work / "target.mp4", work / "pack")
    angles = turn_motion()
    truth = render_clip(face, work / "performer.mp4", np.zeros((len(angles), 3)), angles)
    # self-reenactment: the rest frame is the reference, the target's own rest pose is the performer's
    # (absolute=false), and its lips are as they are (the portrait's rest face shows its teeth)
    same = (
        "--input",
        f"target={pack}",
        "--set",
        "compensate.neutral_frame=0",
        "--set",
        "compensate.close_lips=false",
        "--set",
        "head3d.absolute=false",
    )
    runner("pipeline_3d.yaml", work / "performer.mp4", work / "depth", work / "cache", *same)
    runner(
        "pipeline.yaml",
        work / "performer.mp4",
        work / "similarity",
        work / "cache",
        *same,
        "--set",
        "synthesize.head_motion=similarity",
    )
    manifest = yaml.safe_load((pack / "pack.yaml").read_text())
    W, H = manifest["image_size"]
    a, b, tx, ty = manifest["neutral"]["similarity"]
    M = np.array([[a, -b, tx], [b, a, ty]])
    turned = np.flatnonzero(np.abs(angles[:, :2]).max(1) > TURNED_DEG)
    outputs = {"": work / "depth" / "exr", "_2dsim": work / "similarity" / "exr", "3d": work / "depth" / "render3d"}
    scores: dict[str, list[list[float]]] = {k: [] for k in outputs}
    fills: dict[str, list[float]] = {"pushpull": [], "telea": [], "pushpull_ms": [], "telea_ms": []}
    shown = {}
    for t in range(len(angles)):
        true = cv2.warpAffine(truth["frames"][t], M, (W, H), flags=cv2.INTER_LINEAR).astype(np.float32) / 255.0
        region = cv2.warpAffine(
            face_region(truth["points"][t], truth["frames"].shape[1:3]).astype(np.uint8), M, (W, H), flags=cv2.INTER_NEAREST
        ).astype(bool)
        images = {k: plate_srgb(read_exr(folder / f"frame.{t:06d}.exr")[0]) for k, folder in outputs.items()}
        if t in turned:
            for k, image in images.items():
                scores[k].append([psnr(image, true), psnr(image, true, region), ssim(image, true), ssim(image, true, region)])
            fill_scores(read_exr(outputs[""] / f"frame.{t:06d}.exr")[0], true, fills)
        shown[t] = (true, images)
    rows = [row("shot_turn_frames", len(turned), "frames")]
    means = {k: np.mean(v, axis=0) for k, v in scores.items()}
    for k, (p_all, p_face, s_all, s_face) in means.items():
        stem = "shot_turn3d" if k == "3d" else "shot_turn"
        suffix = "" if k == "3d" else k
        rows += [
            row(f"{stem}_psnr_db{suffix}", p_all, "dB"),
            row(f"{stem}_psnr_db{suffix}_face", p_face, "dB"),
            row(f"{stem}_ssim{suffix}", s_all, "ratio"),
            row(f"{stem}_ssim{suffix}_face", s_face, "ratio"),
        ]
    rows += [row("shot_fill_frames", len(fills["pushpull"]), "frames")]
    if fills["pushpull"]:
        rows += [
            row("shot_fill_psnr_db_pushpull", np.mean(fills["pushpull"]), "dB"),
            row("shot_fill_psnr_db_telea", np.mean(fills["telea"]), "dB"),
            row("shot_fill_ms_pushpull", np.mean(fills["pushpull_ms"]), "ms"),
            row("shot_fill_ms_telea", np.mean(fills["telea_ms"]), "ms"),
        ]
    rows += [
        row("shot_turn_gain_db", means[""][0] - means["_2dsim"][0], "dB"),
        row("shot_turn_gain_db_face", means[""][1] - means["_2dsim"][1], "dB"),
        row("shot_turn3d_gap_db", means["3d"][0] - means[""][0], "dB"),
    ]
    picks = [int(turned[np.argmax(np.abs(angles[turned, k]))]) for k in (0, 1)]
    tiles = []
    for t in picks:
        true, images = shown[t]
        for label, image in (("truth", true), ("2D", images[""]), ("2D similarity", images["_2dsim"]), ("3D", images["3d"])):
            tiles.append((f"{label} yaw {angles[t, 0]:+.0f} pitch {angles[t, 1]:+.0f}", (image * 255).round().astype(np.uint8)))
    write_png(work / "sheet.png", contact_sheet(tiles, columns=4, thumb_height=256))
    return rows


def fill_scores(channels: dict[str, np.ndarray], true: np.ndarray, fills: dict[str, list[float]]) -> None:
    """Push-pull (the pipeline's, :func:`stages.fill.fill_invalid`) and ``cv2.inpaint`` (Telea,
    radius 3 px) of the same frame's filled pixels (``filled.A`` > 0.5), each from the plate's real
    pixels, against the truth there: PSNR (dB) and CPU ms, appended to ``fills`` (frames with
    fewer than 50 such pixels are skipped)."""
    import cv2
    from stages.fill import fill_invalid

    missing = channels["filled.A"] > 0.5
    if missing.sum() < 50:
        return
    plate = plate_srgb(channels).astype(np.float32)
    valid = (~missing).astype(np.float32)
    start = time.thread_time()
    pushed = fill_invalid(plate, valid)
    fills["pushpull_ms"].append(1000 * (time.thread_time() - start))
    start = time.thread_time()
    telea = cv2.inpaint(np.round(plate * 255).astype(np.uint8), missing.astype(np.uint8), 3, cv2.INPAINT_TELEA)
    fills["telea_ms"].append(1000 * (time.thread_time() - start))
    fills["pushpull"].append(psnr(pushed, true, missing))
    fills["telea"].append(psnr(telea.astype(np.float32) / 255.0, true, missing))


# -- head pose slopes ------------------------------------------------------------------------------

AXES = ("yaw", "pitch", "roll")


def pose_motion(frames_sweep: int = 32) -> np.ndarray:
    """``(T, 3)`` yaw, pitch, roll (deg): :func:`turn_motion`, then sweeps of yaw +-35, pitch +-20
    and roll +-25 deg, each alone."""
    s = np.sin(2 * np.pi * np.arange(frames_sweep) / frames_sweep)
    zero = 0 * s
    wide = [np.column_stack([35 * s, zero, zero]), np.column_stack([zero, 20 * s, zero]), np.column_stack([zero, zero, 25 * s])]
    return np.concatenate([turn_motion(), *wide])


def compensated_pose(clip: Path, cache: Path, *overrides: str) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """``pipeline.yaml`` on ``clip`` up to ``compensate``; its ``pose`` bundle and the landmarker's
    facial transformation matrices ``(T, 4, 4)``."""
    from runner.cache import CacheStore
    from runner.config import bind_inputs, load_pipeline
    from runner.execute import Options, Runner
    from runner.registry import Registry

    pipeline = load_pipeline(
        REPO / "pipeline.yaml", Registry.from_entry_points(), overrides=[f"compensate.{o}" for o in overrides]
    )
    executor = Runner(
        pipeline, bind_inputs(pipeline, clip=clip, named=[]), Options(cache=CacheStore(cache), until=("compensate",))
    )
    executor.run()
    pose = executor.values[("compensate", "pose")].load()
    marks = executor.values[("landmarks", "landmarks")].load()
    return {k: np.asarray(v) for k, v in pose.items()}, np.asarray(marks["matrix"])


def slopes(ours: np.ndarray, reference: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``(3,)``: per axis, the slope of the least-squares line of ``ours`` on ``reference`` (both
    ``(T, 3)`` deg) over the ``valid`` frames."""
    return np.array([np.polyfit(reference[valid, k], ours[valid, k], 1)[0] for k in range(3)])


def relative_ypr(R: np.ndarray, reference: int) -> np.ndarray:
    """``(T, 3)`` yaw, pitch, roll (deg, ``R = Ry Rx Rz``) of rotations ``R (T, 3, 3)`` relative to frame ``reference``."""
    from stages.geometry.rotation import ypr_yxz

    return ypr_yxz(R @ R[reference].T)


def pose_rows(work: Path, clips: list[Path]) -> list[dict[str, Any]]:
    """The head pose part (module docstring)."""
    from lab.realface.clip import fit_real_face
    from stages.eigen.facegen.render import rotation
    from stages.geometry.rotation import landmarker_rotation

    work.mkdir(parents=True, exist_ok=True)
    face = fit_real_face(512, backdrop=True)
    angles = pose_motion()
    render_clip(face, work / "pose.mp4", np.zeros((len(angles), 3)), angles)
    truth_R = np.stack([rotation(*a) for a in angles])
    rows = []
    for mode, suffix in (("landmarker", ""), ("points", "_points")):
        pose, _ = compensated_pose(work / "pose.mp4", work / "cache", "neutral_frame=0", f"pose_rotation={mode}")
        truth = relative_ypr(truth_R, int(pose["neutral_frame"]))
        rows += [
            row(f"shot_pose_slope_{axis}{suffix}", v, "ratio")
            for axis, v in zip(AXES, slopes(pose["ypr_deg"], truth, pose["valid"]))
        ]
        worst = {axis: 1.0 for axis in AXES}
        for clip in clips:
            pose, matrix = compensated_pose(clip, work / "cache", f"pose_rotation={mode}")
            landmarker = relative_ypr(landmarker_rotation(matrix), int(pose["neutral_frame"]))
            for axis, v in zip(AXES, slopes(pose["ypr_deg"], landmarker, pose["valid"])):
                rows.append(row(f"shot_pose_slope_{axis}_mp_{clip.stem}{suffix}", v, "ratio"))
                worst[axis] = v if abs(v - 1) > abs(worst[axis] - 1) else worst[axis]
        rows += [row(f"shot_pose_slope_{axis}_mp{suffix}", worst[axis], "ratio") for axis in AXES]
    return rows


# -- invented pixels -------------------------------------------------------------------------------


def indicator_pack(pack: Path, out: Path) -> Path:
    """A copy of ``pack`` whose images are white where they come from inside their footage's frame
    and black where from beyond it, from each entry's recorded similarity and the footage size (the
    writer's images and mattes are not read)."""
    import cv2
    import yaml

    shutil.rmtree(out, ignore_errors=True)
    shutil.copytree(pack, out)
    manifest = yaml.safe_load((pack / "pack.yaml").read_text())
    W, H = manifest["image_size"]
    fw, fh = manifest["source"]["size"]
    inside = np.full((fh, fw), 255, np.uint8)
    for entry in [manifest["neutral"], manifest["standard"], *manifest["examples"], *manifest["teeth_examples"]]:
        a, b, tx, ty = entry["similarity"]
        image = cv2.warpAffine(
            inside,
            np.array([[a, -b, tx], [b, a, ty]]),
            (W, H),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        cv2.imwrite(str(out / entry["image"]), cv2.merge([image] * 3))
        (out / entry["matte"]).unlink(missing_ok=True)
        entry.pop("matte")
    (out / "pack.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False), encoding="utf-8")
    return out


def invented_fraction(pack: Path, out: Path) -> tuple[float, float]:
    """(invented, filled) fractions of a run's output pixels (module docstring)."""
    from stages.actor_pack import load_pack
    from stages.mesh3d.model import target_depth
    from stages.synthesis.build import build_synthesis_model
    from stages.synthesis.synthesize import HeadTurn, Synthesizer

    indicator = load_pack(indicator_pack(pack, out.parent / f"{out.name}_indicator"))
    model = build_synthesis_model(indicator)
    synth = Synthesizer(model, padding_mode="zeros")
    names = np.array(indicator.layout.point_names)
    depth, *_ = target_depth(indicator.model3d, indicator.neutral.points, indicator.intrinsics, names)
    xy = np.load(out / "data" / "data.npz")["target_xy"]
    invented = filled = 0.0
    for t in range(len(xy)):
        channels, spec = read_exr(out / "exr" / f"frame.{t:06d}.exr")
        R = np.array(spec.getattribute("exmap:head_R"), np.float64).reshape(3, 3)
        shift = np.array(spec.getattribute("exmap:head_t_mm"), np.float64)
        rgba, _, _ = synth.render_rgba(
            xy[t : t + 1], turn=HeadTurn(R[None], shift[None], depth, indicator.intrinsics), fill=False
        )
        beyond = 1.0 - rgba[0, 0].numpy()
        invented += float(np.clip(beyond - channels["filled.A"], 0.0, None).mean())
        filled += float(channels["filled.A"].mean())
    return invented / len(xy), filled / len(xy)


def invented_rows(work: Path, clips: list[Path], targets: list[Path]) -> list[dict[str, Any]]:
    """The invented-pixel part (module docstring)."""
    packs = [build_pack(t, work / "packs" / t.stem) for t in targets]
    rows, worst = [], 0.0
    for clip in clips:
        fractions = []
        for pack, target in zip(packs, targets):
            out = work / clip.stem / target.stem
            runner("pipeline.yaml", clip, out, work / "cache", "--input", f"target={pack}")
            fractions.append(invented_fraction(pack, out))
        invented, filled = np.mean(fractions, axis=0)
        worst = max(worst, invented)
        rows += [
            row(f"shot_invented_px_frac_{clip.stem}", invented, "ratio"),
            row(f"shot_filled_px_frac_{clip.stem}", filled, "ratio"),
        ]
    return rows + [row("shot_invented_px_frac_max", worst, "ratio")]


# -- speed and size --------------------------------------------------------------------------------


def speed_rows(work: Path, clip: Path, pack: Path, label: str) -> list[dict[str, Any]]:
    """``pipeline.yaml`` end to end from an empty cache: frames/s, peak memory, cache, profile."""
    from scripts.bench_e2e import folder_bytes

    shutil.rmtree(work / label, ignore_errors=True)
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    seconds, events = runner("pipeline.yaml", clip, work / label / "out", work / label / "cache", "--input", f"target={pack}")
    peak_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    frames = max(int(e["frames"]) for e in events if e.get("event") == "stage" and e.get("frames"))
    rows = [
        row(f"shot_fps_{label}", frames / seconds, "frames/s"),
        row(f"shot_peak_mb_{label}", max(peak_kb, before) / 1024.0, "MB"),
        row(f"shot_cache_mb_per_100_frames_{label}", folder_bytes(work / label / "cache") / 1e6 / frames * 100.0, "MB"),
    ]
    cpu: dict[str, set[float]] = {}
    for e in events:  # a stage run in a child process is reported by the child and again by the run
        if e.get("event") == "stage" and e.get("status") in ("ran", "on demand") and e.get("cpu_seconds"):
            cpu.setdefault(e["stage"], set()).add(float(e["cpu_seconds"]))
    for stage, spent in cpu.items():
        rows.append(row(f"shot_ms_per_frame_{stage}_{label}", 1000.0 * sum(spent) / frames, "ms"))
    # the baseline in the same run: traditional expression mapping (the neutral warped, the 2D
    # similarity, the face-only EXR), everything else as above
    shutil.rmtree(work / f"{label}_baseline", ignore_errors=True)
    base, _ = runner(
        "pipeline.yaml",
        clip,
        work / f"{label}_baseline" / "out",
        work / f"{label}_baseline" / "cache",
        "--input",
        f"target={pack}",
        "--set",
        "synthesize.mode=warp-only",
        "--set",
        "synthesize.head_motion=similarity",
        "--set",
        "exr.layers=face",
    )
    rows += [
        row(f"shot_fps_{label}_warponly", frames / base, "frames/s"),
        row(f"shot_fps_{label}_ratio_warponly", base / seconds, "ratio"),
    ]
    return rows


# -- contact sheets --------------------------------------------------------------------------------


def sheet(clip: Path, pack: Path, work: Path) -> Path:
    """performer | 2D | 3D at the largest yaw, pitch and roll of ``clip`` (``pipeline_3d.yaml``)."""
    from scripts.bench_real import read_frames
    from stages.packbuild.writing import contact_sheet, write_png

    out = work / clip.stem
    runner("pipeline_3d.yaml", clip, out, work / "cache", "--input", f"target={pack}")
    ypr = np.load(out / "data" / "data.npz")["pose_ypr_deg"]
    performer = read_frames(clip)
    tiles = []
    for k, name in enumerate(("yaw", "pitch", "roll")):
        t = int(np.argmax(np.abs(ypr[:, k])))
        label = f"f{t} {name} {ypr[t, k]:+.0f}"
        tiles.append((f"{label} performer", performer[t]))
        for kind, folder in (("2D", "exr"), ("3D", "render3d")):
            image = plate_srgb(read_exr(out / folder / f"frame.{t:06d}.exr")[0])
            tiles.append((f"{label} {kind}", (image * 255).round().astype(np.uint8)))
    path = work / f"{clip.stem}.png"
    write_png(path, contact_sheet(tiles, columns=3, thumb_height=256))
    return path


def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(prog="bench.py shot")
    parser.add_argument("--clip", type=Path, action="append", help="performer clip (repeatable; default every dev clip)")
    parser.add_argument("--target-clip", type=Path, action="append", help="footage to build a pack from (repeatable)")
    parser.add_argument("--no-turn", action="store_true")
    parser.add_argument("--no-pose", action="store_true")
    parser.add_argument("--no-invented", action="store_true")
    parser.add_argument("--no-speed", action="store_true")
    parser.add_argument("--sheets", action="store_true")
    parser.add_argument("--speed-clip", type=Path, default=DEV_CLIPS / "LP_d3.mp4")
    parser.add_argument("--wide-clip", type=Path, default=DEV_CLIPS / "LP_d13.mp4")
    parser.add_argument("--wide-width", type=int, default=1024)
    options = parser.parse_args(args.extra)
    work = Path(args.work) / BENCH
    clips = options.clip or sorted(DEV_CLIPS.glob("*.mp4"))
    targets = options.target_clip or [DEV_CLIPS / f"{name}.mp4" for name in TARGET_CLIPS]
    rows: list[dict[str, Any]] = []
    if not options.no_turn:
        rows += turn_rows(work / "turn")
    if not options.no_pose:
        rows += pose_rows(work / "pose", clips)
    if not options.no_invented:
        rows += invented_rows(work / "invented", clips, targets)
    if not options.no_speed:
        narrow = build_pack(targets[0], work / "packs" / targets[0].stem)
        wide = build_pack(
            options.wide_clip,
            work / "packs" / f"{options.wide_clip.stem}_{options.wide_width}",
            "--set",
            f"pack.width={options.wide_width}",
            "--set",
            "pack.max_upscale=4",
        )
        rows += speed_rows(work / "speed", options.speed_clip, narrow, "384")
        rows += speed_rows(work / "speed", options.speed_clip, wide, str(options.wide_width))
    if options.sheets:
        pack = build_pack(targets[0], work / "packs" / targets[0].stem)
        for clip in clips:
            sheet(clip, pack, work / "sheets")
    return rows
