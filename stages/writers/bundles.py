"""Checks on the bundles a writer is handed: required fields present, one row per frame."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from runner.bundle import BundleType
from runner.stage import StageError
from stages.geometry.bundles import HEAD_POSES, POINTS, SIMILARITY
from stages.occlusion.bundles import OCCLUSION
from stages.synthesis.bundles import COEFFICIENTS

# Per writer kind (the key of the tables below, which names columns, files and EXR attributes):
# the bundle types a writer's port of that kind takes.
TYPES: dict[str, BundleType | tuple[BundleType, ...]] = {
    "points": POINTS,
    "pose": HEAD_POSES,
    "similarity": SIMILARITY,
    "coefficients": COEFFICIENTS,
    "occlusion": OCCLUSION,
}

# Per port type: the fields a writer reads, and which of them have one row per frame.
FIELDS = {
    "points": ("xy", "valid", "names"),
    "pose": ("rvec", "tvec", "reproj_err_px", "valid"),
    "similarity": ("params", "residual_px", "valid"),
    "coefficients": ("coeff", "subregions", "examples"),
    "occlusion": ("regions", "occluded", "score", "valid"),
}
PER_FRAME = {
    "points": ("xy", "valid"),
    "pose": ("rvec", "tvec", "reproj_err_px", "valid"),
    "similarity": ("params", "residual_px", "valid"),
    "coefficients": ("coeff",),
    "occlusion": ("occluded", "score", "valid"),
}


def first_axis(bundle: Mapping[str, np.ndarray], kind: str) -> int:
    """Frame count of a bundle of port type ``kind`` (length of its first per-frame field)."""
    return len(bundle[PER_FRAME[kind][0]]) if PER_FRAME[kind][0] in bundle else 0


def check_bundle(bundle: Mapping[str, np.ndarray], *, stage: str, port: str, kind: str, frames: int) -> None:
    """Raise :class:`StageError` unless ``bundle`` has the fields of ``kind``, each per-frame one
    with ``frames`` rows.

    Parameters
    ----------
    bundle : the input value (dict of arrays).
    stage, port : names for the message (``write.exr``, ``pose``).
    kind : port type, a key of ``FIELDS``.
    frames : expected frame count T.
    """
    missing = [key for key in FIELDS[kind] if key not in bundle]
    if missing:
        raise StageError(f"{stage}: input '{port}' ({kind}) lacks field(s) {', '.join(missing)}")
    for key in PER_FRAME[kind]:
        if np.ndim(bundle[key]) == 0 or len(bundle[key]) != frames:
            raise StageError(
                f"{stage}: input '{port}' field '{key}' has shape {np.shape(bundle[key])}, expected {frames} frames first"
            )
