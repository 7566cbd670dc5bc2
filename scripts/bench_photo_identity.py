"""Bench area ``photo_identity``: how well the face-shape signature of
:mod:`stages.packbuild.identity` tells photos of another person in a folder.

``python scripts/bench.py photo_identity --json [--clip PATH ...] [--stride N] [--folders N] [--max-distance D]``
(default: every clip of ``../shared/dev-clips/``, every 2nd frame, 50 folders per pair). Each
clip is one person; its frames (landmarked one by one, as photos are) stand for photos of that
person with varied expressions and head poses.

Rows: per clip, the distance of each frame's signature to the clip's median signature
(``identity_same_p50_<clip>``, ``_p99_``, ``_max_``). Then folders as
:func:`stages.packbuild.identity.majority_outliers` sees them: 20 random frames of one clip
with 3 of another, for every ordered pair of clips, ``--folders`` times:
``identity_false_alarm_rate`` (the majority's photos named as different),
``identity_detection_rate`` (the intruders named), and ``identity_detection_rate_<a>_<b>`` per
pair (majority ``a``, intruders ``b``), at the threshold ``--max-distance`` (default
``DIFFERENT_FACE_DISTANCE``, the ``photos.identity`` stage's).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from stages.landmarks.landmarker import Landmarker
from stages.packbuild.identity import DIFFERENT_FACE_DISTANCE, face_signature, majority_outliers, signature_distance
from runner.stage import Context
from stages.video import VideoDecode, probe

DEV_CLIPS = Path(__file__).resolve().parents[2] / "shared" / "dev-clips"
MAJORITY, INTRUDERS = 20, 3


def clip_signatures(path: Path, *, stride: int) -> np.ndarray:
    """Signatures ``(F, P)`` of every ``stride``-th frame of ``path`` that has a face, each frame
    searched on its own (as the photos of a folder are)."""
    decode, ctx = VideoDecode(), Context(device="cpu", files_dir=lambda port: Path())
    rows = []
    with Landmarker() as landmarker:
        for t in range(0, probe(path).frames, stride):
            landmarker.reset()
            mesh = landmarker.detect(decode.process(t, t + 1, {"video": path}, {}, ctx)["frames"][0])
            if mesh.valid:
                rows.append(face_signature(mesh.xy[None], mesh.z[None])[0])
    return np.array(rows)


def run(args: argparse.Namespace) -> list[dict]:
    parser = argparse.ArgumentParser(prog="bench.py photo_identity")
    parser.add_argument("--clip", type=Path, action="append", help="a clip of one person (repeatable)")
    parser.add_argument("--stride", type=int, default=2, help="every N-th frame")
    parser.add_argument("--folders", type=int, default=50, help="simulated folders per ordered pair of clips")
    parser.add_argument("--max-distance", type=float, default=DIFFERENT_FACE_DISTANCE, help="the threshold tried")
    extra = parser.parse_args(args.extra)
    clips = extra.clip or sorted(DEV_CLIPS.glob("*.mp4"))
    signatures = {clip.stem: clip_signatures(clip, stride=extra.stride) for clip in clips}
    rows: list[dict] = []

    def row(metric: str, value: float, unit: str = "") -> None:
        rows.append({"bench": "photo_identity", "metric": metric, "value": float(value), "unit": unit})

    for name, s in signatures.items():
        same = signature_distance(s, np.median(s, axis=0))
        row(f"identity_frames_{name}", len(s), "frames")
        for q in (50, 99):
            row(f"identity_same_p{q}_{name}", np.percentile(same, q))
        row(f"identity_same_max_{name}", same.max())
    rng = np.random.default_rng(0)
    named_same, named_other = [], []
    for a, sa in signatures.items():
        for b, sb in signatures.items():
            if a == b:
                continue
            caught = []
            for _ in range(extra.folders):
                folder = np.concatenate(
                    [sa[rng.choice(len(sa), MAJORITY, replace=False)], sb[rng.choice(len(sb), INTRUDERS, replace=False)]]
                )
                differs = majority_outliers(folder, threshold=extra.max_distance)[1]
                named_same.append(differs[:MAJORITY])
                caught.append(differs[MAJORITY:])
            named_other.extend(caught)
            row(f"identity_detection_rate_{a}_{b}", np.mean(caught))
    if named_other:
        row("identity_false_alarm_rate", np.mean(named_same))
        row("identity_detection_rate", np.mean(named_other))
    row("identity_threshold", extra.max_distance)
    return rows
