"""The face regions whose occlusion is judged, and which feature points each covers.

A region is named by the layout's point prefixes (``stages/layouts/zhang134.yaml``): ``eye_l`` is
the eye on the image's left (the viewer's left in a frontal image). Its *outline* is a layout
subregion's polygon (Sec. 5.3), used to measure how much of the region an occluder hides.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

#: region -> the point-name prefixes it covers (teeth and lid creases move with the mouth and eye).
REGION_PREFIXES: dict[str, tuple[str, ...]] = {
    "mouth": ("mouth_", "teeth_"),
    "eye_l": ("eye_l_", "crease_l_"),
    "eye_r": ("eye_r_", "crease_r_"),
    "brow_l": ("brow_l_",),
    "brow_r": ("brow_r_",),
    "nose": ("nose_",),
}
REGIONS: tuple[str, ...] = tuple(REGION_PREFIXES)

#: region -> the layout subregion whose polygon outlines it.
REGION_OUTLINES: dict[str, str] = {
    "mouth": "lips",
    "eye_l": "eye_l",
    "eye_r": "eye_r",
    "brow_l": "brow_l",
    "brow_r": "brow_r",
    "nose": "nose",
}


def region_points(names: Sequence[str]) -> np.ndarray:
    """Which feature points each region covers.

    Parameters
    ----------
    names : (N,) str
        The points bundle's point names.

    Returns
    -------
    (R, N) bool
        Row ``r`` is True at the points whose name starts with one of ``REGIONS[r]``'s prefixes
        (:data:`REGION_PREFIXES`); a layout without such points has an all-False row.
    """
    names = [str(n) for n in names]
    return np.array([[n.startswith(REGION_PREFIXES[r]) for n in names] for r in REGIONS], bool).reshape(len(REGIONS), len(names))
