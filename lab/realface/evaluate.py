"""MediaPipe's landmarks on a rendered clip against its truth: mean error per point group.

    python -m lab.realface.evaluate CLIP TRUTH [--model PATH]

prints, per group (:func:`landmarks.point_groups`) and over all points, the mean and 95th
percentile distance (px) between MediaPipe's landmarks on each decoded frame and the truth's
``points``, over the points the truth marks visible.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from stages.video import VideoDecode, probe

from .landmarks import MODEL_PATH, detect, open_landmarker, point_groups


def landmark_errors(
    frames: np.ndarray, truth_points: np.ndarray, visible: np.ndarray, *, model_path: Path | str = MODEL_PATH
) -> np.ndarray:
    """Distances ``(T, 478)`` px between MediaPipe's landmarks on ``frames`` ``(T, H, W, 3)``
    uint8 and ``truth_points`` ``(T, 478, 2)``; NaN where ``visible`` ``(T, 478)`` is False or
    no face was found."""
    out = np.full(visible.shape, np.nan)
    with open_landmarker(model_path=model_path) as landmarker:
        for f, image in enumerate(frames):
            found = detect(landmarker, image)
            if found is not None:
                out[f] = np.linalg.norm(found[:, :2] - truth_points[f], axis=1)
    out[~visible] = np.nan
    return out


def summarize(errors: np.ndarray) -> dict[str, tuple[float, float]]:
    """``{group: (mean, 95th percentile)}`` px of ``errors`` ``(T, 478)`` (NaN ignored), plus ``all``."""
    groups = {**point_groups(), "all": np.arange(errors.shape[1])}
    return {
        name: (float(np.nanmean(errors[:, idx])), float(np.nanpercentile(errors[:, idx], 95))) for name, idx in groups.items()
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="MediaPipe landmarks vs the truth of a real-texture clip")
    parser.add_argument("clip", type=Path)
    parser.add_argument("truth", type=Path)
    parser.add_argument("--model", type=Path, default=MODEL_PATH)
    args = parser.parse_args(argv)
    with np.load(args.truth, allow_pickle=False) as z:
        points, visible = z["points"], z["visible"]
    info = probe(args.clip)
    frames = VideoDecode().process(0, info.frames, {"video": str(args.clip)}, {}, None)["frames"]
    errors = landmark_errors(frames, points, visible, model_path=args.model)
    print(
        f"{args.clip}: {info.frames} frames {info.width}x{info.height}, faces found in "
        f"{int(np.sum(np.any(np.isfinite(errors), axis=1)))}"
    )
    for name, (mean, p95) in summarize(errors).items():
        print(f"{name:8s} mean {mean:6.2f} px   p95 {p95:6.2f} px")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
