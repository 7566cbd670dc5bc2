"""Write a small synthetic clip (a moving colour gradient with a bright square), e.g. the
committed runner fixture: `python scripts/make_test_clip.py fixtures/clips/tiny.mp4`.

The content is a pure function of the frame index, so the same arguments give the same frames.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from stages.video import VideoWriter


def synthetic_frames(start: int, stop: int, *, width: int, height: int) -> np.ndarray:
    """Frames ``[start, stop)`` as ``(B, height, width, 3)`` uint8 RGB."""
    yy, xx = np.mgrid[:height, :width]
    out = np.empty((stop - start, height, width, 3), np.uint8)
    for k, i in enumerate(range(start, stop)):
        out[k, ..., 0] = (xx * 255 // max(width - 1, 1) + 3 * i) % 256
        out[k, ..., 1] = (yy * 255 // max(height - 1, 1) + 2 * i) % 256
        out[k, ..., 2] = (128 + 64 * np.sin(i / 5.0) + 0 * xx).astype(np.uint8)
        size = max(4, min(width, height) // 5)
        x0 = (5 * i) % max(width - size, 1)
        y0 = (3 * i) % max(height - size, 1)
        out[k, y0 : y0 + size, x0 : x0 + size] = 240
    return out


def write_clip(
    path: Path, *, frames: int, width: int, height: int, fps: float = 25.0, codec: str = "h264", crf: int = 18
) -> Path:
    """Encode :func:`synthetic_frames` ``[0, frames)`` to ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with VideoWriter(path, fps=fps, width=width, height=height, codec=codec, crf=crf) as writer:
        for start in range(0, frames, 32):
            writer.write(synthetic_frames(start, min(start + 32, frames), width=width, height=height))
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("out", type=Path)
    parser.add_argument("--frames", type=int, default=48)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--fps", type=float, default=25.0)
    parser.add_argument("--codec", choices=("h264", "ffv1"), default="h264")
    parser.add_argument("--crf", type=int, default=23)
    args = parser.parse_args()
    write_clip(args.out, frames=args.frames, width=args.width, height=args.height, fps=args.fps, codec=args.codec, crf=args.crf)


if __name__ == "__main__":
    main()
