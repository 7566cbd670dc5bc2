"""MediaPipe Face Landmarker (the project's :mod:`stages.landmarks.landmarker`): the 478
landmarks of a face in px, and the index groups of MediaPipe's face mesh used here.

Pixel origin: MediaPipe's normalized ``(x, y)`` times the image width/height already has its
origin at the centre of the top-left pixel (the project's convention), so ``x_px = x * W``,
``y_px = y * H`` with no half-pixel shift. Measured on the source photo (tests/scripts/
test_realface.py): an image upscaled 2x by pixel replication, whose content sits at
``x2 = 2 x + 0.5`` in centre-origin coordinates, gives landmarks ``0.45 px`` (x and y, mean over
the 478 points, 14 sizes 80..768 px) from ``2 x`` — 0.5 expected for a centre origin, 0 for a
corner one; a horizontal flip gives ``x + x_mirror = W - 1.1`` after removing the face's own
asymmetry (which grows with the image size) — ``W - 1`` expected for a centre origin.
(The landmarker module measured the same with resizes and flips.) MediaPipe's ``z`` is a
relative depth with roughly the scale of ``x``: ``z_px = z * W``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stages.landmarks.landmarker import MODEL_PATH, N_MESH, OUTER_EYE_CORNERS, Landmarker  # noqa: F401 - OUTER_EYE_CORNERS re-exported for mesh.py

N_LANDMARKS = N_MESH

# MediaPipe face-mesh indices ("right" = the subject's right, on the image's left)
NOSE_TIP = 1
CHIN = 152
FOREHEAD = 10
UPPER_LIDS = (159, 386)
CHEEKS = (50, 280)
MOUTH_CORNERS = (61, 291)
LIPS_OUTER_UPPER = (61, 185, 40, 39, 37, 0, 267, 269, 270, 409, 291)
LIPS_OUTER_LOWER = (61, 146, 91, 181, 84, 17, 314, 405, 321, 375, 291)
LIPS_INNER_UPPER = (78, 191, 80, 81, 82, 13, 312, 311, 310, 415, 308)
LIPS_INNER_LOWER = (78, 95, 88, 178, 87, 14, 317, 402, 318, 324, 308)
BROWS = (46, 53, 52, 65, 55, 70, 63, 105, 66, 107, 276, 283, 282, 295, 285, 300, 293, 334, 296, 336)
EYES = (
    33,
    7,
    163,
    144,
    145,
    153,
    154,
    155,
    133,
    173,
    157,
    158,
    159,
    160,
    161,
    246,
    263,
    249,
    390,
    373,
    374,
    380,
    381,
    382,
    362,
    398,
    384,
    385,
    386,
    387,
    388,
    466,
)
IRISES = tuple(range(468, 478))
NOSE = (1, 2, 4, 5, 6, 19, 45, 48, 64, 94, 97, 98, 115, 168, 195, 197, 220, 275, 278, 294, 326, 327, 344, 440)
FACE_OVAL = (
    10,
    338,
    297,
    332,
    284,
    251,
    389,
    356,
    454,
    323,
    361,
    288,
    397,
    365,
    379,
    378,
    400,
    377,
    152,
    148,
    176,
    149,
    150,
    136,
    172,
    58,
    132,
    93,
    234,
    127,
    162,
    21,
    54,
    103,
    67,
    109,
)


def inner_lip_polygon() -> tuple[int, ...]:
    """Indices of the inner lip contour in order around the mouth opening (20 points)."""
    return LIPS_INNER_UPPER + LIPS_INNER_LOWER[-2:0:-1]


def point_groups() -> dict[str, np.ndarray]:
    """Disjoint landmark groups for reporting errors: oval, brows, eyes, irises, nose, lips, other."""
    lips = set(LIPS_OUTER_UPPER + LIPS_OUTER_LOWER + LIPS_INNER_UPPER + LIPS_INNER_LOWER)
    named = {"oval": FACE_OVAL, "brows": BROWS, "eyes": EYES, "irises": IRISES, "nose": NOSE, "lips": tuple(lips)}
    groups = {k: np.array(sorted(v)) for k, v in named.items()}
    used = np.concatenate(list(groups.values()))
    groups["other"] = np.setdiff1d(np.arange(N_LANDMARKS), used)
    return groups


def open_landmarker(*, model_path: Path | str = MODEL_PATH) -> Landmarker:
    """The project's MediaPipe :class:`~stages.landmarks.landmarker.Landmarker`, set to look at
    every image on its own (whole image, no crop around the previous face, no tiles, one face).
    Use as a context manager."""
    path = Path(model_path)
    if not path.is_file():
        raise ValueError(f"model_path: expected a face_landmarker.task file, got {path} (no such file)")
    return Landmarker(model_path=path, max_faces=1, crop_scale=0, search_tiles=False)


def detect(landmarker: Landmarker, rgb: np.ndarray) -> np.ndarray | None:
    """Landmarks of the face in ``rgb`` ``(H, W, 3)`` uint8.

    Returns
    -------
    numpy.ndarray or None
        ``(478, 3)`` float64: x, y px (origin at the centre of the top-left pixel), z px
        (MediaPipe's relative depth times W; smaller = nearer the camera); None when no face
        is found.
    """
    found = landmarker.detect(rgb)
    if not found.valid:
        return None
    return np.column_stack([found.xy, found.z])
