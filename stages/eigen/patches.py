"""Feature patches cut in the neutral's frame (Valente & Dugelay: "image patches for the facial
features of interest", the datasets D_{i,j}).

The paper assumes the feature locations and the head pose known. Here a patch is a fixed
rectangle of the performer's *neutral* image (frame 0 / the pack's neutral, where the layout's
feature points are known) and a frame is sampled through the 2D similarity ``T`` of eq. 8 of the
main paper (Zhang et al.), which maps the neutral's rigid points onto the frame's: pixel ``u`` of
the patch reads the frame at ``T(u)``. A frame that differs from the neutral only by a similarity
therefore gives the neutral's patch (invariance to translation, in-plane rotation and scale);
out-of-plane rotation is left to the estimator, which gets the head rotation as input.

Pixels: x right, y down, origin at the centre of the top-left pixel (OpenCV's).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.color import luma_float32
from stages.geometry.similarity import apply_similarity

# Features (paper: "the eyes, eyebrows, and the mouth"), by layout point-name prefix. Each eye is
# cut with its brow, crease and under-eye point, as the lids and brows move together in the
# patch; the mouth with the lip-corner folds and the chin, which jaw drop and chin raise move.
FEATURES: dict[str, tuple[str, ...]] = {
    "eye_l": ("brow_l_", "eye_l_", "crease_l_", "under_eye_l"),
    "eye_r": ("brow_r_", "eye_r_", "crease_r_", "under_eye_r"),
    "mouth": ("mouth_outer_", "mouth_inner_", "lipfold_", "chin"),
}


@dataclass(frozen=True)
class FeatureWindow:
    """One feature's patch: a rectangle of the neutral's frame sampled on a regular grid.

    ``points`` are the layout indices defining the feature; ``origin`` ``(2,)`` px is the neutral
    position of patch pixel (0, 0); ``step`` px the neutral distance between patch pixels;
    ``shape`` ``(h, w)`` the patch size in pixels.
    """

    name: str
    points: tuple[int, ...]
    origin: tuple[float, float]
    step: float
    shape: tuple[int, int]

    def grid(self) -> np.ndarray:
        """Neutral-frame positions ``(h, w, 2)`` float64 px of the patch pixels."""
        h, w = self.shape
        ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
        return np.stack([self.origin[0] + self.step * xs, self.origin[1] + self.step * ys], axis=-1)


def feature_points(point_names: tuple[str, ...], prefixes: tuple[str, ...]) -> tuple[int, ...]:
    """Indices of the layout points whose names start with one of ``prefixes``."""
    found = tuple(i for i, n in enumerate(point_names) if n.startswith(prefixes))
    if not found:
        raise ValueError(f"expected layout points named {list(prefixes)}..., got none")
    return found


def feature_windows(
    neutral: np.ndarray,
    point_names: tuple[str, ...],
    *,
    margin: float = 0.25,
    step: float = 1.0,
    features: dict[str, tuple[str, ...]] | None = None,
) -> tuple[FeatureWindow, ...]:
    """The patch of each feature around its neutral points.

    Parameters
    ----------
    neutral : (N, 2) float
        The neutral geometry in px (the frame the patches are cut in).
    point_names : tuple of N str
        Layout point names, in the order of ``neutral``.
    margin : float
        Room around the points' bounding box on each side, as a fraction of the box's larger
        side (the features move: lids close, the jaw drops).
    step : float
        Neutral px between patch pixels (1: the neutral's resolution).
    features : dict, optional
        Feature name -> point-name prefixes; :data:`FEATURES` by default.

    Returns
    -------
    tuple of FeatureWindow
        One per feature, in the order of ``features``.
    """
    neutral = np.asarray(neutral, dtype=np.float64)
    if neutral.ndim != 2 or neutral.shape != (len(point_names), 2):
        raise ValueError(f"expected neutral points ({len(point_names)}, 2), got {neutral.shape}")
    if step <= 0 or margin < 0:
        raise ValueError(f"expected step > 0 and margin >= 0, got step={step}, margin={margin}")
    windows = []
    for name, prefixes in (FEATURES if features is None else features).items():
        idx = feature_points(point_names, prefixes)
        low, high = neutral[list(idx)].min(axis=0), neutral[list(idx)].max(axis=0)
        pad = margin * float((high - low).max())
        low, high = low - pad, high + pad
        shape = tuple(int(np.ceil(v)) + 1 for v in ((high - low) / step)[::-1])
        windows.append(FeatureWindow(name, idx, (float(low[0]), float(low[1])), float(step), shape))
    return tuple(windows)


def luminance(image: np.ndarray) -> np.ndarray:
    """Rec. 601 luma ``(H, W)`` float32 in [0, 1] of an RGB uint8 image ``(H, W, 3)``
    (:func:`stages.color.luma_float32` / 255)."""
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise TypeError(f"expected an RGB uint8 image (H, W, 3), got {image.dtype} {image.shape}")
    return luma_float32(image) / 255.0


def cut_patches(
    image: np.ndarray, similarity: np.ndarray, windows: tuple[FeatureWindow, ...], *, min_inside: float = 0.98
) -> tuple[list[np.ndarray], np.ndarray]:
    """Sample each feature's patch from a frame through the similarity (bilinear).

    Parameters
    ----------
    image : (H, W, 3) uint8
        The frame, RGB.
    similarity : (4,) float
        ``(a, b, tx, ty)`` mapping the neutral's frame onto this frame (eq. 8).
    windows : tuple of FeatureWindow
        From :func:`feature_windows`.
    min_inside : float
        Fewest fraction of a patch's pixels that must fall inside the image for the patch to
        count; a patch with fewer is masked (its feature left out of the analysis).

    Returns
    -------
    patches : list of (h, w) float32
        Luma in [0, 1] per feature; a masked patch is all zeros.
    valid : (p,) bool
        Whether each feature's patch is inside the image.
    """
    import cv2  # here: loading a pipeline must not import OpenCV

    gray = luminance(image)
    H, W = gray.shape
    patches, valid = [], np.zeros(len(windows), dtype=bool)
    for j, window in enumerate(windows):
        at = apply_similarity(np.asarray(similarity, dtype=np.float64), window.grid())
        inside = (at[..., 0] >= -0.5) & (at[..., 0] <= W - 0.5) & (at[..., 1] >= -0.5) & (at[..., 1] <= H - 0.5)
        valid[j] = bool(np.all(np.isfinite(at))) and inside.mean() >= min_inside
        if not valid[j]:
            patches.append(np.zeros(window.shape, np.float32))
            continue
        patches.append(
            cv2.remap(
                gray,
                at[..., 0].astype(np.float32),
                at[..., 1].astype(np.float32),
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            )
        )
    return patches, valid


def patch_vectors(
    image: np.ndarray,
    similarity: np.ndarray,
    windows: tuple[FeatureWindow, ...],
    *,
    blur_px: float = 0.0,
    normalize: bool = False,
    min_inside: float = 0.98,
) -> tuple[list[np.ndarray], np.ndarray]:
    """The patches of :func:`cut_patches`, conditioned and flattened: the vectors the eigenfeatures
    decompose (the same in training and analysis).

    ``blur_px``: Gaussian of that standard deviation (patch px) first, so that a feature a pixel
    off its window changes the vector less; ``normalize``: each patch to zero mean and unit
    standard deviation (shading that changes with the head's rotation). Returns ``p`` vectors
    ``(h w,)`` float32 and ``valid (p,)`` bool; a masked patch stays all zeros.
    """
    import cv2  # here: loading a pipeline must not import OpenCV

    patches, valid = cut_patches(image, similarity, windows, min_inside=min_inside)
    vectors = []
    for P, ok in zip(patches, valid):
        if ok and blur_px > 0:
            P = cv2.GaussianBlur(P, (0, 0), blur_px, borderType=cv2.BORDER_REFLECT)
        if ok and normalize:
            P = (P - P.mean()) / max(float(P.std()), 1e-6)
        vectors.append(P.ravel())
    return vectors, valid
