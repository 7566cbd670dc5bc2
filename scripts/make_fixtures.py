"""Make the synthetic fixture set: actor packs, held-out ground truth, performer clips with truth.

    python scripts/make_fixtures.py --out DIR [--seed N] [--demo] [--combo] [--part PART]
    python scripts/make_fixtures.py render --identity SEED [--controls smile=0.5,jaw_drop=0.3]
        [--pose YAW,PITCH,ROLL[,TX,TY,TZ]] [--size WxH] --out PREFIX

Without ``--demo`` it writes the small CI set (the bytes committed under ``fixtures/``); with
``--demo`` the paper-sized set (600x800 target pack, 300-frame 640x480 clips). The performer is
identity ``N`` and the target identity ``N + 1`` (default N = 1). ``--combo`` adds the
combinatorial target pack ``packs/combo`` (examples moving one facial region each, held-out
expressions combining regions); ``--part`` writes one piece only (e.g. ``--part pack:combo``).
Formats: docs/fixtures.md.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from stages.eigen.facegen.face import CONTROLS, JAW_HINGE_END, expression_points3d, mean_model3d
from lab.facegen.io import Mp4Writer, save_npz, write_named_rows, write_png, write_points_csv
from stages.eigen.facegen.render import (
    NECK_PIVOT,
    Camera,
    FaceModel,
    framing_translation,
    make_camera,
    make_face,
    render,
    rotation,
    texture_ppm,
)
from lab.facegen.sequences import (
    STANDARD,
    TEETH,
    captured_controls,
    clip_trajectory,
    combo_controls,
    controls_of,
    farthest_point_selection,
    similarity_eq9,
)
from stages.eigen.facegen.texture import DETAILS, detail_strengths
from stages.layout import Layout, load_layout

PACK_HEAD_MM = 265.0  # face height spanning a pack image
CLIP_HEAD_MM = 290.0  # looser framing for clips, room for head motion


@dataclass(frozen=True)
class Spec:
    """Sizes of one fixture set: pack image size (W, H), clip size, frames, fps, counts."""

    target_size: tuple[int, int]
    clip_size: tuple[int, int]
    clip_frames: int
    fps: int
    captured: int
    examples: int
    heldout_images: int | None  # None = an image for every held-out expression
    supersample: int


CI = Spec(
    target_size=(240, 320),
    clip_size=(320, 240),
    clip_frames=48,
    fps=30,
    captured=40,
    examples=14,
    heldout_images=6,
    supersample=2,
)
DEMO = Spec(
    target_size=(600, 800),
    clip_size=(640, 480),
    clip_frames=300,
    fps=30,
    captured=40,
    examples=14,
    heldout_images=None,
    supersample=1,
)


def pack_pose(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Frontal pose (R = I) framing the face for a pack image."""
    return np.eye(3), framing_translation(camera, head_mm=PACK_HEAD_MM)


def write_pack(
    folder: Path,
    face: FaceModel,
    camera: Camera,
    R: np.ndarray,
    t: np.ndarray,
    spec: Spec,
    *,
    name: str,
    captured: np.ndarray,
    captured_names: list[str],
    examples: np.ndarray | None = None,
    heldout_images: int | None = None,
) -> dict[str, np.ndarray]:
    """Render and write one actor pack (pack.yaml, images, points, model3d, captured, truth.npz).

    ``captured`` ``(K, C)`` are the controls of the captured expressions, ``captured_names`` their
    names; ``examples`` the rows that become example images (default: ``spec.examples`` rows by
    farthest-point selection over the geometries, Sec. 14); the rest are held out, the first
    ``heldout_images`` of them (None: all) with an image. Returns the pack's truth arrays (also
    written to ``truth.npz``).
    """
    layout = face.layout
    names = layout.point_names
    ss = spec.supersample

    images: list[tuple[str, np.ndarray]] = []
    cap_vis: dict[int, np.ndarray] = {}

    def save(key: str, controls: np.ndarray, sub: str = "images", *, captured: int | None = None) -> dict[str, str]:
        """Render one expression, write its image (and points unless held out); return its manifest entry."""
        p3 = expression_points3d(face.neutral, controls, layout)
        r = render(face, p3, R, t, camera, supersample=ss)
        write_png(folder / sub / f"{key}.png", r.image)
        if captured is not None:
            cap_vis[captured] = r.visible
        if sub == "heldout":
            return {"image": f"{sub}/{key}.png"}
        write_points_csv(folder / "points" / f"{key}.csv", names, r.points)
        images.append((key, r.image))
        return {"name": key, "image": f"{sub}/{key}.png", "points": f"points/{key}.csv"}

    entries: dict[str, object] = {"neutral": save("neutral", controls_of())}
    standard_c = controls_of(**STANDARD)
    entries["standard"] = save("standard", standard_c)
    cap_c = captured
    cap_p3 = np.stack([expression_points3d(face.neutral, c, layout) for c in cap_c])
    cap_pts = np.stack([render_points(p, R, t, camera) for p in cap_p3])
    neutral_pts = render_points(face.neutral, R, t, camera)
    if examples is None:
        examples = farthest_point_selection((cap_pts - neutral_pts).reshape(len(cap_pts), -1), spec.examples)
    chosen = np.asarray(examples, dtype=np.int64)
    heldout = np.setdiff1d(np.arange(len(cap_c)), chosen)
    cap_names = list(captured_names)
    entries["examples"] = [save(cap_names[k], cap_c[k], captured=int(k)) for k in chosen]
    teeth_c = np.stack([controls_of(**c) for c in TEETH])
    entries["teeth_examples"] = [save(f"teeth{k}", c) for k, c in enumerate(teeth_c)]
    limit = len(heldout) if heldout_images is None else heldout_images
    held_paths = [
        save(cap_names[k], cap_c[k], "heldout", captured=int(k))["image"] if j < limit else "" for j, k in enumerate(heldout)
    ]
    for k in range(len(cap_c)):
        if k not in cap_vis:  # no image written: visibility from a cheap render
            cap_vis[k] = render(face, cap_p3[k], R, t, camera, supersample=1).visible
    save_npz(folder / "captured.npz", {"points": cap_pts, "names": np.array(cap_names)})
    write_named_rows(folder / "model3d.csv", names, mean_model3d(layout), ("x", "y", "z"))
    truth = {
        "identity_seed": np.array(face.identity.seed),
        "point_names": np.array(names),
        "control_names": np.array(CONTROLS),
        "R": R,
        "t": t,
        "intrinsics": camera.A,
        "neutral_points3d": face.neutral,
        "standard_controls": standard_c,
        "teeth_controls": teeth_c,
        "captured_names": np.array(cap_names),
        "captured_controls": cap_c,
        "captured_points3d": cap_p3,
        "captured_points": cap_pts,
        "captured_visible": np.stack([cap_vis[k] for k in range(len(cap_c))]),
        "example_index": chosen.astype(np.int64),
        "heldout_index": heldout.astype(np.int64),
        "heldout_image": np.array(held_paths),
    }
    save_npz(folder / "truth.npz", truth)
    write_manifest(folder / "pack.yaml", name=name, layout=layout, camera=camera, entries=entries, seed=face.identity.seed)
    write_contact_sheet(folder.parent.parent / f"{name}_sheet.png", images)
    return truth


def render_points(points3d: np.ndarray, R: np.ndarray, t: np.ndarray, camera: Camera) -> np.ndarray:
    """Projections ``(N, 2)`` px of head-frame points (eq. 10), without rendering an image."""
    cam = points3d @ R.T + t
    img = cam @ camera.A.T
    return img[:, :2] / img[:, 2:3]


def write_manifest(path: Path, *, name: str, layout: Layout, camera: Camera, entries: dict, seed: int) -> None:
    """Write ``pack.yaml`` (fixed key order, no timestamps)."""

    def entry(e: dict) -> str:
        return "{" + ", ".join(f"{k}: {v}" for k, v in e.items()) + "}"

    a = camera.A
    lines = [
        "# Actor pack made by scripts/make_fixtures.py (synthetic identity); format: docs/fixtures.md",
        "format: actor-pack/1",
        f"name: {name}",
        f"layout: {layout.name}",
        f"image_size: [{camera.size[0]}, {camera.size[1]}]",
        "intrinsics:  # camera matrix A of eq. 10, px",
        *[f"  - [{a[r, 0]:.6f}, {a[r, 1]:.6f}, {a[r, 2]:.6f}]" for r in range(3)],
        "model3d: model3d.csv  # generic face model (mean shape), mm, head frame",
        f"neutral: {entry(entries['neutral'])}",
        f"standard: {entry(entries['standard'])}  # mouth open",
        "examples:",
        *[f"  - {entry(e)}" for e in entries["examples"]],
        "teeth_examples:",
        *[f"  - {entry(e)}" for e in entries["teeth_examples"]],
        "captured: captured.npz  # points (K, N, 2) px, all captured geometries (examples included)",
        f"generator: {{identity_seed: {seed}, truth: truth.npz}}",
    ]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def _label(img: np.ndarray, text: str) -> np.ndarray:
    out = img.copy()
    cv2.putText(out, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(out, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def write_contact_sheet(path: Path, images: list[tuple[str, np.ndarray]], *, columns: int = 6, thumb_h: int = 200) -> None:
    """A labelled grid of thumbnails ``thumb_h`` px high."""
    thumbs = []
    for name, img in images:
        h, w = img.shape[:2]
        thumbs.append(_label(cv2.resize(img, (int(round(w * thumb_h / h)), thumb_h), interpolation=cv2.INTER_AREA), name))
    tw = thumbs[0].shape[1]
    rows = []
    for r in range(0, len(thumbs), columns):
        row = thumbs[r : r + columns]
        row += [np.full_like(thumbs[0], 255)] * (columns - len(row))
        rows.append(np.hstack([np.pad(t, ((2, 2), (2, 2), (0, 0)), constant_values=255) for t in row]))
    write_png(path, np.vstack(rows)[:, : columns * (tw + 4)])


def write_clip(
    folder: Path,
    kind: str,
    performer: FaceModel,
    target: FaceModel,
    camera: Camera,
    t0: np.ndarray,
    target_camera: Camera,
    target_R: np.ndarray,
    target_t: np.ndarray,
    spec: Spec,
) -> None:
    """Render a performer clip with its ground truth (``<kind>.mp4``, ``<kind>_truth.npz``,
    ``<kind>_track0.csv``) and a strip of frames (``<kind>_strip.png`` next to ``folder``)."""
    layout = performer.layout
    T = spec.clip_frames
    controls, angles, shift = clip_trajectory(kind, T, spec.fps)
    n = layout.n_points
    pts = np.zeros((T, n, 2))
    vis = np.zeros((T, n), dtype=bool)
    p3d = np.zeros((T, n, 3))
    Rs = np.zeros((T, 3, 3))
    ts = np.zeros((T, 3))
    expr_pts = np.zeros((T, n, 2))
    tgt_pts = np.zeros((T, n, 2))
    tgt_p3d = np.zeros((T, n, 3))
    strengths = np.zeros((T, len(DETAILS)))
    neutral_pts = render_points(performer.neutral, np.eye(3), t0, camera)
    writer = Mp4Writer(folder / f"{kind}.mp4", camera.size, spec.fps)
    strip_at = set(np.linspace(0, T - 1, 6).round().astype(int).tolist())
    strip = []
    for f in range(T):
        R = rotation(*angles[f])
        t = t0 + shift[f] + NECK_PIVOT - R @ NECK_PIVOT  # X_cam = R (X - pivot) + pivot + t0 + shift
        p = expression_points3d(performer.neutral, controls[f], layout)
        r = render(performer, p, R, t, camera, supersample=spec.supersample, ppm=texture_ppm(camera, t0[2]))
        writer.write(r.image)
        pts[f], vis[f], p3d[f], Rs[f], ts[f] = r.points, r.visible, p, R, t
        expr_pts[f] = render_points(p, np.eye(3), t0, camera)
        tp = expression_points3d(target.neutral, controls[f], layout)
        tgt_p3d[f] = tp
        tgt_pts[f] = render_points(tp, target_R, target_t, target_camera)
        st = detail_strengths(performer.neutral, p, layout)
        strengths[f] = [st[d] for d in DETAILS]
        if f in strip_at:
            strip.append(_strip_frame(r.image, r.points[list(layout.tracked)], f))
    writer.close()
    rigid = np.array(layout.rigid)
    sim = np.stack([similarity_eq9(neutral_pts[rigid], pts[f, rigid]) for f in range(T)])
    rvec = np.stack([cv2.Rodrigues(R)[0].ravel() for R in Rs])
    save_npz(
        folder / f"{kind}_truth.npz",
        {
            "point_names": np.array(layout.point_names),
            "control_names": np.array(CONTROLS),
            "detail_names": np.array(DETAILS),
            "fps": np.array(float(spec.fps)),
            "size": np.array(camera.size, dtype=np.int64),
            "intrinsics": camera.A,
            "points": pts,
            "visible": vis,
            "points3d": p3d,
            "R": Rs,
            "rvec": rvec,
            "tvec": ts,
            "angles_deg": angles,
            "neutral_points": neutral_pts,
            "expression_points": expr_pts,
            "similarity": sim,
            "rigid": rigid.astype(np.int64),
            "tracked": np.array(layout.tracked, dtype=np.int64),
            "controls": controls,
            "detail_strengths": strengths,
            "target_points": tgt_pts,
            "target_points3d": tgt_p3d,
            "target_intrinsics": target_camera.A,
            "target_R": target_R,
            "target_t": target_t,
            "target_size": np.array(target_camera.size, dtype=np.int64),
        },
    )
    tracked = list(layout.tracked)
    write_points_csv(
        folder / f"{kind}_track0.csv", [layout.point_names[i] for i in tracked], pts[0, tracked], frame_size=camera.size
    )
    write_png(folder.parent / f"{kind}_strip.png", np.hstack(strip))


def _strip_frame(image: np.ndarray, tracked: np.ndarray, frame: int) -> np.ndarray:
    out = image.copy()
    for x, y in tracked:
        cv2.circle(out, (int(round(x * 4)), int(round(y * 4))), 4, (40, 230, 80), -1, cv2.LINE_AA, 2)
    return np.pad(_label(out, f"frame {frame}"), ((2, 2), (2, 2), (0, 0)), constant_values=255)


PARTS = ("clip:live", "clip:calm", "pack:performer", "pack:target")  # independent pieces, slowest first
COMBO = "pack:combo"  # the combinatorial target pack, made with --combo


def make_part(out: Path, part: str, *, seed: int, spec: Spec) -> None:
    """Write one piece of the fixture set (see :data:`PARTS`); pieces share nothing but the seed."""
    layout = load_layout("zhang134")
    clip_cam = make_camera(spec.clip_size)
    t0 = framing_translation(clip_cam, head_mm=CLIP_HEAD_MM)
    target_cam = make_camera(spec.target_size)
    tR, tt = pack_pose(target_cam)
    kind, _, name = part.partition(":")
    if part in ("pack:performer", "pack:target"):
        identity = seed if name == "performer" else seed + 1
        camera, R, t = (clip_cam, np.eye(3), t0) if name == "performer" else (target_cam, tR, tt)
        controls = captured_controls(
            np.random.default_rng(np.random.SeedSequence([identity, 1])),
            spec.captured,
            jaw_max=1.0 if name == "target" else JAW_HINGE_END,
        )
        write_pack(
            out / "packs" / name,
            make_face(identity, layout),
            camera,
            R,
            t,
            spec,
            name=name,
            captured=controls,
            captured_names=[f"cap{k:02d}" for k in range(len(controls))],
            heldout_images=spec.heldout_images,
        )
    elif part == COMBO:
        controls, names, n_examples = combo_controls()
        write_pack(
            out / "packs" / "combo",
            make_face(seed + 1, layout),
            target_cam,
            tR,
            tt,
            spec,
            name="combo",
            captured=controls,
            captured_names=names,
            examples=np.arange(n_examples),
        )
    elif kind == "clip":
        write_clip(
            out / "clips", name, make_face(seed, layout), make_face(seed + 1, layout), clip_cam, t0, target_cam, tR, tt, spec
        )
    else:
        raise ValueError(f"unknown part {part!r}; known: {', '.join(PARTS + (COMBO,))}")


def make_set(
    out: Path, *, seed: int = 1, demo: bool = False, spec: Spec | None = None, jobs: int = 1, combo: bool = False
) -> None:
    """Write the whole fixture set for performer ``seed``, target ``seed + 1``.

    ``spec`` defaults to :data:`DEMO` with ``demo`` else :data:`CI` (tests pass a smaller one).
    ``combo`` adds the combinatorial pack ``packs/combo`` (:data:`COMBO`). ``jobs > 1`` runs the
    parts in that many worker processes (``--part``; the standard specs only); the bytes are the
    same either way.
    """
    parts = PARTS + ((COMBO,) if combo else ())
    if jobs <= 1 or spec is not None:
        for part in parts:
            make_part(out, part, seed=seed, spec=spec or (DEMO if demo else CI))
        return
    base = [sys.executable, str(Path(__file__).resolve()), "--out", str(out), "--seed", str(seed)] + (["--demo"] if demo else [])
    running: list[tuple[str, subprocess.Popen]] = []
    failed = []
    for part in parts:
        if len(running) >= jobs:
            name, proc = running.pop(0)
            if proc.wait() != 0:
                failed.append(name)
        running.append((part, subprocess.Popen(base + ["--part", part])))
    failed += [name for name, proc in running if proc.wait() != 0]
    if failed:
        raise RuntimeError(f"fixture parts failed: {', '.join(failed)}")


def render_identity(
    seed: int,
    controls: dict[str, float] | np.ndarray | None = None,
    *,
    yaw: float = 0.0,
    pitch: float = 0.0,
    roll: float = 0.0,
    translation: tuple[float, float, float] = (0.0, 0.0, 0.0),
    size: tuple[int, int] = (240, 320),
    head_mm: float = PACK_HEAD_MM,
    supersample: int = 2,
) -> dict[str, np.ndarray]:
    """Render identity ``seed`` at the given controls and pose, returning image and truth.

    The camera is :func:`make_camera` of ``size``; the pose is ``R = rotation(yaw, pitch, roll)``
    and ``t = framing_translation(head_mm) + translation`` (mm). With the defaults it matches the
    target pack's images of ``--seed seed - 1``. Returns ``image (H, W, 3) uint8``,
    ``points (N, 2)``, ``visible (N,)``, ``points3d (N, 3)``, ``R``, ``t``, ``intrinsics``,
    ``controls (C,)``.
    """
    layout = load_layout("zhang134")
    face = make_face(seed, layout)
    if controls is None:
        c = controls_of()
    elif isinstance(controls, dict):
        c = controls_of(**controls)
    else:
        c = np.asarray(controls, dtype=np.float64)
    camera = make_camera(size)
    R = rotation(yaw, pitch, roll)
    t = framing_translation(camera, head_mm=head_mm) + np.asarray(translation, dtype=np.float64)
    p3 = expression_points3d(face.neutral, c, layout)
    r = render(face, p3, R, t, camera, supersample=supersample)
    return {
        "image": r.image,
        "points": r.points,
        "visible": r.visible,
        "points3d": p3,
        "R": R,
        "t": t,
        "intrinsics": camera.A,
        "controls": c,
    }


def _render_main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="make_fixtures.py render", description="render one identity with its ground truth")
    parser.add_argument("--identity", type=int, required=True, help="identity seed")
    parser.add_argument("--controls", default="", help=f"name=value,... of {', '.join(CONTROLS)}")
    parser.add_argument("--pose", default="0,0,0", help="yaw,pitch,roll in degrees [,tx,ty,tz in mm]")
    parser.add_argument("--size", default="240x320", help="WxH in pixels")
    parser.add_argument("--out", type=Path, required=True, help="output prefix: writes PREFIX.png and PREFIX.npz")
    args = parser.parse_args(argv)
    controls = {}
    for item in filter(None, args.controls.split(",")):
        key, _, value = item.partition("=")
        if key not in CONTROLS:
            parser.error(f"unknown control {key!r}; known: {', '.join(CONTROLS)}")
        controls[key] = float(value)
    pose = [float(v) for v in args.pose.split(",")]
    if len(pose) not in (3, 6):
        parser.error("--pose takes 3 or 6 numbers")
    w, _, h = args.size.partition("x")
    res = render_identity(
        args.identity,
        controls,
        yaw=pose[0],
        pitch=pose[1],
        roll=pose[2],
        translation=tuple(pose[3:]) if len(pose) == 6 else (0.0, 0.0, 0.0),
        size=(int(w), int(h)),
    )
    write_png(args.out.with_suffix(".png"), res["image"])
    layout = load_layout("zhang134")
    save_npz(
        args.out.with_suffix(".npz"),
        {
            **{k: v for k, v in res.items() if k != "image"},
            "point_names": np.array(layout.point_names),
            "control_names": np.array(CONTROLS),
        },
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "render":
        return _render_main(argv[1:])
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="output folder (packs/, clips/, *.png)")
    parser.add_argument("--seed", type=int, default=1, help="performer identity seed; the target is seed + 1")
    parser.add_argument("--demo", action="store_true", help="paper-sized set: 600x800 target, 300-frame 640x480 clips")
    parser.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    parser.add_argument(
        "--combo",
        action="store_true",
        help="also write packs/combo: one-region examples, held-out combinations (docs/fixtures.md)",
    )
    parser.add_argument("--part", choices=PARTS + (COMBO,), help="write only this piece of the set")
    args = parser.parse_args(argv)
    if args.part:
        make_part(args.out, args.part, seed=args.seed, spec=DEMO if args.demo else CI)
    else:
        make_set(args.out, seed=args.seed, demo=args.demo, jobs=args.jobs, combo=args.combo)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
