"""3D benchmark: Sec. 9 mesh synthesis and Sec. 14.1 rendering against the fixture generator's truth.

The target pack (default ``fixtures/packs/target``) has a ``truth.npz``: the generator's identity,
the 3D points of every captured expression and the pack camera. Everything is measured on the
held-out expressions (captured, not examples), each given by its TRUE 2D geometry, as the 2D
synthesis benchmark does.

Geometry (pack camera frame, mm, mean over the skin points and the held-out expressions):

* ``mesh3d_vertex_err_mm``: the Sec. 9 synthesis (per-subregion QP on the 3D examples, vertex
  blending) against the true 3D points;
* ``mesh3d_vertex_err_mm_lifted``: the 2D geometry lifted at the model's depths (no QP);
* ``mesh3d_depth_err_mm_neutral``: the model's neutral (the depth source alone);
* ``mesh3d_vertex_err_mm_centred`` (and ``_lifted_centred``): the error after removing each
  expression's mean offset (shape error without the global depth offset of the generic model's
  scale); ``_centred_noise2px``: the same with 2 px of Gaussian noise on the input 2D points (the
  2D pipeline's geometry is never exact), where the projection onto the examples' hull helps;
* the depth sources compared (:func:`depth_source_rows`): ``mesh3d_shape_err_mm_generic`` /
  ``_mediapipe`` (neutral depth relief), ``mesh3d_expr_dz_err_mm_mediapipe`` next to
  ``mesh3d_expr_dz_mm_true`` (examples' depth change from the neutral).

Rendering — ``--frames`` frames (default 16), each a held-out expression at a head pose with yaw
spread over [-25, 25] degrees (pitch and roll up to 6 and 4 degrees). The TRUE pose is given to
both outputs (the rows measure the 3D model and the renderer, not pose estimation). The texture
of both is the 2D pipeline's synthesized expression image (``Synthesizer``, frontal, no head
motion):

* ``render3d_psnr_db``: the 3D render (Sec. 9 mesh moved by the pose, MSAA 4x, alpha composited
  over the generator's background) against the generator's own render of the target at that pose
  and expression, sRGB PSNR over the true face region (the hull of the projected true points),
  over the frames with |yaw| > 10 degrees; ``render3d_psnr_db_2d``: the 2D output (the same
  synthesized image moved by the eq. 8 similarity fitted to the true rigid points, as the 2D
  pipeline carries head motion) on the same frames and pixels; ``_all`` suffixes: all frames.

Speed (2 CPU threads, llvmpipe without a GPU; the load average is printed):

* ``mesh3d_fps``: frames/s of the Sec. 9 synthesis (lift, QP for all subregions, blending),
  100 frames per call;
* ``render3d_fps``: frames/s of rendering at 600x800 (MSAA 4x, colour and depth passes, read
  back); ``render3d_fps_facegen``: the generator's numpy/OpenCV renderer at the same size in
  the same run (baseline), ``render3d_speedup`` their ratio.

A contact sheet (truth | 3D render | 2D output) goes to ``<work>/render3d/render3d_bench_sheet.png``.

    python scripts/bench.py render3d --json [--pack fixtures/packs/target] [--frames 16]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from stages.eigen.facegen.render import Camera, background, make_face, render, rotation  # noqa: E402
from stages.actor_pack import load_pack  # noqa: E402
from stages.geometry.compensate import fit_similarity  # noqa: E402
from stages.mesh3d.model import build_target_model, lift  # noqa: E402
from stages.mesh3d.synthesis import synthesize_3d  # noqa: E402
from stages.render3d.frame import render_textured, scaled_intrinsics  # noqa: E402
from stages.render3d.head import apply_head  # noqa: E402
from stages.render3d.raster import MeshRenderer  # noqa: E402
from stages.color import linear_to_srgb, srgb_to_linear  # noqa: E402
from stages.synthesis.build import build_synthesis_model  # noqa: E402
from stages.synthesis.synthesize import Synthesizer  # noqa: E402

SPEED_SIZE = (600, 800)
YAW_THRESHOLD_DEG = 10.0


def row(metric: str, value: float, unit: str) -> dict:
    return {"bench": "render3d", "metric": metric, "value": float(value), "unit": unit}


def poses(n: int, seed: int = 3) -> np.ndarray:
    """``(n, 3)`` (yaw, pitch, roll) degrees: yaw spread over [-25, 25], small pitch and roll."""
    rng = np.random.default_rng(seed)
    yaw = np.linspace(-25.0, 25.0, n)
    return np.column_stack([yaw, rng.uniform(-6, 6, n), rng.uniform(-4, 4, n)])


def face_hull(points: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: the convex hull of projected points (N, 2) px."""
    mask = np.zeros((size[1], size[0]), np.uint8)
    cv2.fillConvexPoly(mask, np.round(cv2.convexHull(points.astype(np.float32))[:, 0] * 16).astype(np.int32), 1, cv2.LINE_8, 4)
    return mask.astype(bool)


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """PSNR (dB) of two (H, W, 3) images in [0, 1] over ``mask`` (H, W)."""
    mse = float(np.mean((a[mask].astype(np.float64) - b[mask]) ** 2))
    return float("inf") if mse == 0 else -10.0 * np.log10(mse)


def geometry_rows(model, truth: dict, skin: np.ndarray, *, noise_px: float = 2.0) -> tuple[list[dict], np.ndarray]:
    """Vertex errors of the held-out expressions; returns the rows and the Sec. 9 vertices."""
    R, t = truth["R"], truth["t"]
    held = truth["heldout_index"]
    true3d = truth["captured_points3d"][held] @ R.T + t
    g2 = truth["captured_points"][held]
    lifted = lift(g2, model.depth, model.camera)
    sec9, _ = synthesize_3d(model.examples, lifted, model.members)
    noisy = lift(g2 + np.random.default_rng(0).normal(0.0, noise_px, g2.shape), model.depth, model.camera)
    sec9_noisy, _ = synthesize_3d(model.examples, noisy, model.members)
    neutral = truth["neutral_points3d"] @ R.T + t

    def err(x: np.ndarray, *, centred: bool = False) -> float:
        d = (x - (neutral if x.ndim == 2 else true3d))[..., skin, :]
        if centred:
            d = d - d.mean(-2, keepdims=True)
        return float(np.linalg.norm(d, axis=-1).mean())

    tag = f"noise{noise_px:g}px"
    rows = [
        row("mesh3d_vertex_err_mm", err(sec9), "mm"),
        row("mesh3d_vertex_err_mm_lifted", err(lifted), "mm"),
        row("mesh3d_depth_err_mm_neutral", err(model.neutral), "mm"),
        row("mesh3d_vertex_err_mm_centred", err(sec9, centred=True), "mm"),
        row("mesh3d_vertex_err_mm_lifted_centred", err(lifted, centred=True), "mm"),
        row(f"mesh3d_vertex_err_mm_centred_{tag}", err(sec9_noisy, centred=True), "mm"),
        row(f"mesh3d_vertex_err_mm_lifted_centred_{tag}", err(noisy, centred=True), "mm"),
    ]
    return rows, sec9


def depth_source_rows(pack, model, truth: dict, skin: np.ndarray) -> list[dict]:
    """The depth sources compared: the posed generic model vs MediaPipe's mesh depth over the pack images.

    ``mesh3d_shape_err_mm_generic`` / ``_mediapipe``: neutral depth relief (each centred on its
    mean) against the truth; ``mesh3d_expr_dz_err_mm_mediapipe``: the examples' depth change from
    the neutral by MediaPipe against the true change, next to ``mesh3d_expr_dz_mm_true`` (the error
    of taking no change, as the model does). MediaPipe's relative depth (px of x) is scaled to mm
    at the model's mean face depth.
    """
    from stages.landmarks.correspondence import layout_from_mesh, load_correspondence
    from stages.landmarks.landmarker import Landmarker

    corr = load_correspondence("zhang134_mediapipe", layout=pack.layout)
    with Landmarker() as landmarker:
        z = []
        for image in [pack.neutral.image] + [e.image for e in pack.examples]:
            landmarker.reset()
            z.append(landmarker.detect(image).z)
    mp = layout_from_mesh(np.stack(z)[..., None], corr)[..., 0] * model.depth[skin].mean() / model.camera[0, 0]
    R, t = truth["R"], truth["t"]
    neutral = (truth["neutral_points3d"] @ R.T + t)[:, 2]
    names = list(truth["captured_names"])
    examples = (truth["captured_points3d"][[names.index(str(n)) for n in model.example_names]] @ R.T + t)[..., 2]
    true_dz = (examples - neutral)[:, skin]

    def shape(z: np.ndarray) -> float:
        a, b = z[skin] - z[skin].mean(), neutral[skin] - neutral[skin].mean()
        return float(np.abs(a - b).mean())

    return [
        row("mesh3d_shape_err_mm_generic", shape(model.depth), "mm"),
        row("mesh3d_shape_err_mm_mediapipe", shape(mp[0]), "mm"),
        row("mesh3d_expr_dz_err_mm_mediapipe", float(np.abs((mp[1:] - mp[0])[:, skin] - true_dz).mean()), "mm"),
        row("mesh3d_expr_dz_mm_true", float(np.abs(true_dz).mean()), "mm"),
    ]


def run(args: argparse.Namespace) -> list[dict]:
    parser = argparse.ArgumentParser(prog="bench.py render3d")
    parser.add_argument("--pack", type=Path, default=ROOT / "fixtures/packs/target")
    parser.add_argument("--frames", type=int, default=16)
    opts = parser.parse_args(args.extra)
    pack = load_pack(opts.pack)
    truth = dict(np.load(opts.pack / "truth.npz", allow_pickle=False))
    model = build_target_model(pack, pack.model3d, pack.intrinsics)
    skin = np.array([not n.startswith("teeth_") for n in model.names])
    rows, sec9 = geometry_rows(model, truth, skin)
    rows += depth_source_rows(pack, model, truth, skin)

    face = make_face(int(truth["identity_seed"]), pack.layout)
    size = pack.image_size
    camera = Camera(np.asarray(truth["intrinsics"]), size)
    synth = Synthesizer(build_synthesis_model(pack))
    held = truth["heldout_index"]
    R0, t0 = truth["R"], truth["t"]
    renderer = MeshRenderer(size, samples=4)
    bg = background(size)
    rigid = list(pack.layout.rigid)
    scores: dict[str, list[float]] = {"3d": [], "2d": []}
    yaws, sheet = [], []
    for k, (yaw, pitch, roll) in enumerate(poses(opts.frames)):
        j = k % len(held)
        p3 = truth["captured_points3d"][held[j]]
        R = rotation(yaw, pitch, roll) @ R0
        true_img = render(face, p3, R, t0, camera, supersample=2).image.astype(np.float32) / 255.0
        true_pts = (p3 @ R.T + t0) @ camera.A.T
        true_pts = true_pts[:, :2] / true_pts[:, 2:3]
        mask = face_hull(true_pts[skin], size)
        g2 = truth["captured_points"][held[j]]
        rgb, alpha, _ = synth.render(g2[None])
        texture = rgb[0].permute(1, 2, 0).numpy()
        matte = alpha[0, 0].numpy()
        # 3D: X' = R R0^T (X - t0) + t0 (the true head motion about the head origin)
        Rm = R @ R0.T
        v = apply_head(sec9[j], Rm, t0 - Rm @ t0)
        rgba, _ = render_textured(renderer, v, model.triangles, g2, texture, model.camera, mask=matte)
        over = rgba[..., :3] + (1.0 - rgba[..., 3:]) * srgb_to_linear(bg)
        out3d = np.clip(linear_to_srgb(over), 0, 1)
        # 2D: the synthesized image moved by the eq. 8 similarity of the rigid points
        a, b, tx, ty = fit_similarity(g2[rigid], true_pts[rigid])
        M = np.array([[a, -b, tx], [b, a, ty]])
        out2d = cv2.warpAffine(texture, M, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        scores["3d"].append(psnr(out3d, true_img, mask))
        scores["2d"].append(psnr(out2d, true_img, mask))
        yaws.append(yaw)
        if len(sheet) < 4 and abs(yaw) > YAW_THRESHOLD_DEG:
            sheet.append(np.hstack([true_img, out3d, out2d]))
    renderer.release()
    big = np.abs(np.array(yaws)) > YAW_THRESHOLD_DEG
    for key, suffix in (("3d", ""), ("2d", "_2d")):
        s = np.array(scores[key])
        rows.append(row(f"render3d_psnr_db{suffix}", s[big].mean(), "dB"))
        rows.append(row(f"render3d_psnr_db{suffix}_all", s.mean(), "dB"))
    if sheet:
        folder = args.work / "render3d"
        folder.mkdir(parents=True, exist_ok=True)
        img = np.clip(np.vstack(sheet) * 255 + 0.5, 0, 255).astype(np.uint8)
        cv2.imwrite(str(folder / "render3d_bench_sheet.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    rows += speed_rows(model, sec9, truth, face, camera, pack)
    return rows


def speed_rows(model, sec9: np.ndarray, truth: dict, face, camera: Camera, pack) -> list[dict]:
    """Frames/s of the Sec. 9 synthesis and of rendering at 600x800 (with the facegen baseline)."""
    import torch

    torch.set_num_threads(2)
    load = os.getloadavg()[0]
    held = truth["heldout_index"]
    g2 = np.resize(truth["captured_points"][held], (100,) + truth["captured_points"].shape[1:])
    synthesize_3d(model.examples, lift(g2[:4], model.depth, model.camera), model.members)  # warm-up
    t = time.perf_counter()
    synthesize_3d(model.examples, lift(g2, model.depth, model.camera), model.members)
    mesh_fps = len(g2) / (time.perf_counter() - t)
    scale = SPEED_SIZE[0] / pack.image_size[0]
    A = scaled_intrinsics(model.camera, scale)
    texture = cv2.resize(pack.standard.image, SPEED_SIZE, interpolation=cv2.INTER_LINEAR).astype(np.float32) / 255.0
    uv = truth["captured_points"][held[0]] * scale + 0.5 * scale - 0.5
    renderer = MeshRenderer(SPEED_SIZE, samples=4)
    render_textured(renderer, sec9[0], model.triangles, uv, texture, A)  # warm-up
    n = 20
    t = time.perf_counter()
    for k in range(n):
        render_textured(renderer, sec9[k % len(sec9)], model.triangles, uv, texture, A)
    render_fps = n / (time.perf_counter() - t)
    renderer.release()
    big_camera = Camera(A, SPEED_SIZE)
    p3 = truth["captured_points3d"][held[0]]
    render(face, p3, truth["R"], truth["t"], big_camera, supersample=1)  # texture built once
    m = 3
    t = time.perf_counter()
    for _ in range(m):
        render(face, p3, truth["R"], truth["t"], big_camera, supersample=1)
    base_fps = m / (time.perf_counter() - t)
    return [
        row("mesh3d_fps", mesh_fps, "frames/s"),
        row("render3d_fps", render_fps, "frames/s"),
        row("render3d_fps_facegen", base_fps, "frames/s"),
        row("render3d_speedup", render_fps / base_fps, "x"),
        row("loadavg_1min", load, ""),
    ]


def contact_sheet(clip: Path, out: Path, png: Path, *, frames: tuple[int, ...] = (0, 12, 24, 36), height: int = 160) -> None:
    """Rows of performer | 2D result | 3D render for a ``pipeline_3d.yaml`` run published under ``out``.

    Reads the clip, ``out/video/result.mp4`` and ``out/video3d/result3d.mp4``; writes a small PNG.
    """
    import av

    def decode(path: Path) -> list[np.ndarray]:
        with av.open(str(path)) as container:
            return [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]

    columns = [decode(clip), decode(out / "video" / "result.mp4"), decode(out / "video3d" / "result3d.mp4")]
    rows = []
    for f in frames:
        cells = [
            cv2.resize(c[f], (round(c[f].shape[1] * height / c[f].shape[0]), height), interpolation=cv2.INTER_AREA)
            for c in columns
        ]
        rows.append(np.hstack(cells))
    cv2.imwrite(str(png), cv2.cvtColor(np.vstack(rows), cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])


if __name__ == "__main__":
    cli = argparse.ArgumentParser(description="contact sheet of a pipeline_3d.yaml run: performer | 2D result | 3D render")
    cli.add_argument("clip", type=Path)
    cli.add_argument("out", type=Path, help="the run's --out folder")
    cli.add_argument("png", type=Path)
    a = cli.parse_args()
    contact_sheet(a.clip, a.out, a.png)
