"""Write a real-texture ground-truth clip: the astronaut portrait's face with known head pose and
expressions (lab/realface, docs/realface.md).

    python scripts/make_realface.py --out DIR --frames 48 --seed 0 [--size 512] [--lossless] [--backdrop]

writes ``DIR/astro.mp4`` (H.264 yuv420p, 25 fps, crf 12; ``--lossless``: FFV1 ``astro.mkv``) and
``DIR/astro_truth.npz``. Same arguments, same truth. ``--backdrop``: the head (face, hair, ears,
neck) moves in front of a static background (the photo with the head inpainted) instead of the
whole picture moving with it.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lab.realface.clip import make_clip
from lab.realface.landmarks import MODEL_PATH


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--frames", type=int, default=48, help="number of frames")
    parser.add_argument("--seed", type=int, default=0, help="motion seed")
    parser.add_argument("--size", type=int, default=512, help="frame side, px (even)")
    parser.add_argument("--fps", type=int, default=25)
    parser.add_argument("--crf", type=int, default=12, help="x264 constant rate factor (H.264 only)")
    parser.add_argument("--lossless", action="store_true", help="FFV1 lossless .mkv instead of H.264 .mp4")
    parser.add_argument("--supersample", type=int, default=2, help="samples per pixel along each axis")
    parser.add_argument("--name", default="astro", help="file name stem")
    parser.add_argument("--model", type=Path, default=MODEL_PATH, help="MediaPipe face_landmarker.task")
    parser.add_argument("--backdrop", action="store_true", help="a static background behind the moving head")
    args = parser.parse_args(argv)
    wall, cpu = time.perf_counter(), time.process_time()
    try:
        clip, truth = make_clip(
            args.out,
            frames=args.frames,
            seed=args.seed,
            size=args.size,
            fps=args.fps,
            codec="ffv1" if args.lossless else "h264",
            crf=args.crf,
            supersample=args.supersample,
            name=args.name,
            model_path=args.model,
            backdrop=args.backdrop,
        )
    except ValueError as exc:
        print(f"make_realface: {exc}", file=sys.stderr)
        return 2
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    print(
        f"{clip}\n{truth}\n{args.frames} frames {args.size}x{args.size} in {wall:.1f} s wall, {cpu:.1f} s CPU "
        f"({args.frames / wall:.1f} frames/s wall, fit and encoding included)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
