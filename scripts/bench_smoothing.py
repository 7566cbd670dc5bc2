"""Trajectory smoothing on synthetic ground truth: short mouth openings under landmark jitter.

A synthetic face of 48 points, one coordinate each, shares a slow head motion (a sine of 10 px
over 5 s plus a drift of 1.5 px/s); a third of them (the mouth's) open every 40 frames: a
raised-cosine bump (:func:`raised_cosine`) of 3, 4 or 5 frames at half height (zero to zero over
twice that) and an amplitude drawn from 10-40 px per point. White noise of ``sigma`` px (a real
landmarker's jitter: 0.3-1.0 px) is added. The widths are calibrated on a real landmarker's
clips: the Gaussian of sigma 1.5 removes 14-29% of the mouth-opening amplitude there, 18-36% here.

Rows for ``raw`` (no smoothing), ``gaussian`` (``smooth.gaussian``, sigma 1.5), ``one_euro``
(``smooth.one_euro`` with its stage defaults: the face's frame) and ``one_euro_image`` (the same
filter on the image positions, :func:`one_euro_smooth`), each at noise ``sigma`` 0.3 and 1.0 px:

- ``retention_w<W>_<method>_n<sigma>``: the smoothed value at an opening's peak frame minus the
  head motion there, over the opening's amplitude, mean over the openings of width W and the
  mouth's points (1 = kept);
- ``retention_min_w3_a10_<method>_n<sigma>``: the same for 10 px openings of 3 frames only (the
  hardest case of the range), mean over their placements;
- ``jitter_<method>_n<sigma>``: mean |second difference| in px over all points and the frames at
  least W + 3 frames away from any opening (slow head motion only; the truth's own is
  ``jitter_truth``);
- ``rms_<method>_n<sigma>``: RMS distance to the truth over all frames, px.

With ``--clip PATH`` (repeatable; real footage, no truth) the layout's points from MediaPipe's face
mesh (``stages.landmarks``, correspondence ``zhang134_mediapipe``) are smoothed by the same three
methods at the clip's fps, and per clip (suffix ``_<file stem>``):

- ``real_peak_ratio_<method>``: the inner-lip opening (``mouth_inner_8`` below ``mouth_inner_2``)
  smoothed over raw, mean over the 10 frames of widest raw opening (noise on the raw peaks puts
  a perfect smoother slightly under 1);
- ``real_jitter_ratio_<method>``: mean |second difference| of the eye corners and nose points
  about their per-frame mean (face-relative jitter, head motion removed), smoothed over raw.

    python scripts/bench.py smoothing --json [--points 48] [--frames 600] [--fps 30] [--clip PATH ...]
    python scripts/bench_smoothing.py          (the same JSON lines, without the dispatcher)
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from stages.geometry.mapping import NORMALIZATION_POINTS, eye_distance
from stages.geometry.smooth import (
    GaussianSmooth,
    OneEuroSmooth,
    gaussian_smooth,
    one_euro_smooth,
    one_euro_smooth_face,
)

AREA = "smoothing"
WIDTHS = (3, 4, 5)
NOISE_PX = (0.3, 1.0)
SPACING = 40  # frames between opening peaks


def raised_cosine(frames: np.ndarray, *, peak: float, width: float) -> np.ndarray:
    """A unit raised-cosine bump ``(T,)``: 1 at ``peak``, 0.5 at ``peak +- width / 2`` (``width``
    frames at half height), 0 beyond ``peak +- width``."""
    u = (np.asarray(frames, dtype=np.float64) - peak) / width
    return np.where(np.abs(u) < 1.0, 0.5 * (1.0 + np.cos(np.pi * u)), 0.0)


def opening_face(
    n_points: int, n_frames: int, *, fps: float, seed: int = 0, amplitude_px: tuple[float, float] = (10.0, 40.0)
) -> dict[str, np.ndarray]:
    """Noise-free trajectories ``(T, M)`` px of M points of one face: a slow head motion shared by
    all, plus mouth openings on the first ``ceil(M / 3)`` (the mouth's points).

    Returns ``truth (T, M)``, ``head (T, 1)`` (the head motion alone), ``peaks (K,)`` frames,
    ``widths (K,)`` frames (cycling through :data:`WIDTHS`), ``amplitudes (K, ceil(M / 3))`` px
    and ``quiet (T,)`` bool (frames at least width + 3 from every opening).
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames, dtype=np.float64)[:, None]
    head = 10.0 * np.sin(2 * np.pi * t / (5.0 * fps) + rng.uniform(0, 2 * np.pi)) + 1.5 * t / fps
    peaks = np.arange(SPACING, n_frames - SPACING // 2, SPACING)
    widths = np.resize(np.array(WIDTHS), len(peaks))
    mouth = -(-n_points // 3)
    amplitudes = rng.uniform(*amplitude_px, (len(peaks), mouth))
    truth = np.repeat(head, n_points, axis=1)
    quiet = np.ones(n_frames, bool)
    for peak, width, amplitude in zip(peaks, widths, amplitudes):
        truth[:, :mouth] += amplitude * raised_cosine(t, peak=peak, width=width)
        quiet[max(0, peak - width - 3) : peak + width + 4] = False
    return {"truth": truth, "head": head, "peaks": peaks, "widths": widths, "amplitudes": amplitudes, "quiet": quiet}


def retention(smoothed: np.ndarray, clip: dict[str, np.ndarray], width: int) -> float:
    """Mean over the openings of ``width`` frames and the mouth's points of (smoothed - head) /
    amplitude at the peak."""
    pick = clip["widths"] == width
    peaks = clip["peaks"][pick]
    mouth = clip["amplitudes"].shape[1]
    return float(np.mean((smoothed[peaks, :mouth] - clip["head"][peaks]) / clip["amplitudes"][pick]))


def jitter(values: np.ndarray, quiet: np.ndarray) -> float:
    """Mean |second difference| ``|x(t-1) - 2 x(t) + x(t+1)|`` over the quiet frames t, px."""
    return float(np.abs(np.diff(values, n=2, axis=0))[quiet[1:-1]].mean())


def methods(fps: float) -> dict[str, Callable[[np.ndarray], np.ndarray]]:
    """The compared smoothers, each at its stage's default parameters."""
    sigma = next(p.default for p in GaussianSmooth.params if p.name == "sigma")
    euro = {p.name: p.default for p in OneEuroSmooth.params if p.name != "fps"}
    return {
        "raw": lambda x: x,
        "gaussian": lambda x: gaussian_smooth(x, sigma=sigma)[0],
        "one_euro": lambda x: one_euro_smooth_face(x, np.ones(x.shape[:2], bool), fps=fps, **euro)[0],
        "one_euro_image": lambda x: one_euro_smooth(x, fps=fps, **euro)[0],
    }


def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(prog="bench.py smoothing")
    parser.add_argument("--points", type=int, default=48, help="points of the synthetic face")
    parser.add_argument("--frames", type=int, default=600, help="frames per trajectory")
    parser.add_argument("--fps", type=float, default=30.0, help="frames per second")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--clip", type=Path, action="append", default=[], help="real clip (rows real_*)")
    opts = parser.parse_args(getattr(args, "extra", []))

    def row(metric: str, value: float, unit: str) -> dict[str, Any]:
        return {"bench": AREA, "metric": metric, "value": float(value), "unit": unit}

    clip = opening_face(opts.points, opts.frames, fps=opts.fps, seed=opts.seed)
    # the hardest case: 10 px openings, 3 frames wide, at every placement
    small = opening_face(opts.points, opts.frames, fps=opts.fps, seed=opts.seed + 1, amplitude_px=(10.0, 10.0))
    rows = [row("jitter_truth", jitter(clip["truth"], clip["quiet"]), "px")]
    rng = np.random.default_rng(opts.seed + 2)
    for noise in NOISE_PX:
        noisy = clip["truth"] + rng.normal(0.0, noise, clip["truth"].shape)
        noisy_small = small["truth"] + rng.normal(0.0, noise, small["truth"].shape)
        for name, smooth in methods(opts.fps).items():
            smoothed = smooth(noisy)
            tag = f"{name}_n{noise:g}"
            rows += [row(f"retention_w{w}_{tag}", retention(smoothed, clip, w), "ratio") for w in WIDTHS]
            rows += [
                row(f"retention_min_w3_a10_{tag}", retention(smooth(noisy_small), small, 3), "ratio"),
                row(f"jitter_{tag}", jitter(smoothed, clip["quiet"]), "px"),
                row(f"rms_{tag}", np.sqrt(np.mean((smoothed - clip["truth"]) ** 2)), "px"),
            ]
    for path in opts.clip:
        xy, names, fps = clip_points(path)
        opening = inner_lip_opening(xy, names)
        widest = np.argsort(opening)[-10:]
        for name, smooth in methods(fps).items():
            smoothed = smooth(xy)
            rows += [
                row(
                    f"real_peak_ratio_{name}_{path.stem}",
                    np.mean(inner_lip_opening(smoothed, names)[widest] / opening[widest]),
                    "ratio",
                ),
                row(
                    f"real_jitter_ratio_{name}_{path.stem}",
                    face_relative_jitter(smoothed, names) / face_relative_jitter(xy, names),
                    "ratio",
                ),
            ]
    return rows


def clip_points(path: Path) -> tuple[np.ndarray, list[str], float]:
    """The zhang134 points ``(T, N, 2)`` px of a clip's face from MediaPipe's mesh (frames without
    a face dropped), the point names and the clip's fps."""
    import av

    from stages.landmarks.correspondence import layout_from_mesh, load_correspondence
    from stages.landmarks.landmarker import Landmarker
    from stages.layout import load_layout

    layout = load_layout("zhang134")
    correspondence = load_correspondence("zhang134_mediapipe", layout=layout)
    meshes = []
    with av.open(str(path)) as container, Landmarker() as landmarker:
        fps = float(container.streams.video[0].average_rate)
        for frame in container.decode(video=0):
            mesh = landmarker.detect(frame.to_ndarray(format="rgb24"))
            if mesh.valid:
                meshes.append(mesh.xy)
    return layout_from_mesh(np.stack(meshes), correspondence), list(layout.point_names), fps


def inner_lip_opening(xy: np.ndarray, names: list[str]) -> np.ndarray:
    """``(T,)``: ``mouth_inner_8`` below ``mouth_inner_2`` over the first frame's eye distance."""
    gap = xy[:, names.index("mouth_inner_8"), 1] - xy[:, names.index("mouth_inner_2"), 1]
    return gap / eye_distance(xy[0], names)


def face_relative_jitter(xy: np.ndarray, names: list[str]) -> float:
    """Mean |second difference| px of the eye-corner and nose points about their per-frame mean."""
    points = xy[:, [names.index(n) for n in NORMALIZATION_POINTS]]
    return float(np.abs(np.diff(points - points.mean(axis=1, keepdims=True), n=2, axis=0)).mean())


if __name__ == "__main__":
    for result in run(argparse.Namespace(extra=sys.argv[1:])):
        print(json.dumps(result))
