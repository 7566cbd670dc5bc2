"""Which frames of a clip may become part of an actor pack (Sec. 14: the examples are frames of
the target's own footage, so every chosen frame must be frontal enough, sharp and unoccluded).

Per frame, from the face mesh, the layout's points and the pixels:

- **no_face**: the landmarker found no face;
- **out_of_frame**: a layout point lies outside the image (the face is cut by the border);
- **head_pose**: the head's yaw, pitch or roll (degrees, from the landmarker's facial
  transformation matrix) beyond a bound;
- **blur**: the sharpness — variance of the Laplacian of the grey image over the face's skin and
  eyes inside the face's box (the lips and mouth left out: teeth and an open mouth add edges that
  have nothing to do with focus; on the real-texture clip they swing the whole box's variance by a
  factor of 5) — is below a fraction of the clip's median (motion blur, defocus);
- **occlusion**: the mean colour (CIE L*a*b*) of an eye zone or the mean chromaticity (a*, b*) of
  the lips (the ring between the outer and inner lip lines) is farther than a bound (Delta E
  CIE76, or its a*b* part) from its median over the clip's frames that passed the checks above:
  sunglasses, a hand, a microphone, hair over the eyes or mouth. The lips' lightness is left out
  because it changes with the expression itself: the landmarker's inner lip line lies inside the
  real one, so when the mouth opens the lip ring takes in the dark mouth (L* drops by about 30 on
  the real-texture clip while a*, b* move by 5). An eye zone (lids, crease, crow's feet) changes
  little when the eye closes, and a dark occluder shows mostly in lightness.

Each rejected frame gets the first failing cause in that order. Measurements
(:func:`measure_frame`) also give the *teeth fraction* used later to choose teeth examples: the
share of pixels inside the inner lip line that are at least as light as the cheeks' median and
no more coloured than it (teeth are light and nearly grey; lips, tongue and the mouth's inside are
darker or redder).
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

from stages.color import luma_opencv
from stages.geometry.rotation import ypr_yxz
from stages.layout import Layout, subregion_mask

CAUSES = ("no_face", "out_of_frame", "head_pose", "blur", "occlusion")
OCCLUSION_REGIONS = ("eyezone_l", "eyezone_r", "lips")
OCCLUSION_LIGHTNESS = (True, True, False)  # whether L* counts in each region's colour change
SKIN_REGIONS = ("cheek_l", "cheek_r")
KEEP = -1


def head_angles(matrix: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Head yaw, pitch and roll from the landmarker's facial transformation matrices.

    Parameters
    ----------
    matrix : (T, 4, 4) float
        Canonical face mesh -> camera (MediaPipe); the upper-left 3x3 block may carry a scale.
    valid : (T,) bool
        Frames with a face; the others get 0.

    Returns
    -------
    (T, 3) float64
        ``(yaw, pitch, roll)`` in degrees, ``R = Ry(yaw) Rx(pitch) Rz(roll)``; 0 is frontal.
    """
    matrix = np.asarray(matrix, np.float64)
    valid = np.asarray(valid, bool)
    if matrix.ndim != 3 or matrix.shape[1:] != (4, 4) or valid.shape != matrix.shape[:1]:
        raise ValueError(f"expected matrix (T, 4, 4) and valid (T,), got {matrix.shape} and {valid.shape}")
    out = np.zeros((len(matrix), 3))
    if valid.any():
        R = matrix[valid, :3, :3]
        out[valid] = ypr_yxz(R / np.cbrt(np.linalg.det(R))[:, None, None])
    return out


def face_box(points: np.ndarray, size: tuple[int, int]) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)`` integer pixel box (end exclusive) around ``points (N, 2)`` px,
    clipped to the image of ``size = (W, H)``."""
    W, H = size
    lo = np.floor(np.nanmin(points, axis=0)).astype(int)
    hi = np.ceil(np.nanmax(points, axis=0)).astype(int) + 1
    return max(lo[0], 0), max(lo[1], 0), min(hi[0], W), min(hi[1], H)


def laplacian_sharpness(gray: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Variance of the 4-neighbour Laplacian ``[[0, 1, 0], [1, -4, 1], [0, 1, 0]]`` of a grey
    image ``(h, w)`` (values in [0, 255]) over the pixels of ``mask (h, w) bool`` (all if None),
    the image's border rows and columns left out; 0 when no pixel is left."""
    import cv2

    gray = np.asarray(gray, np.float64)
    if gray.ndim != 2:
        raise ValueError(f"expected a grey image (h, w), got shape {gray.shape}")
    inner = np.zeros(gray.shape, bool)
    inner[1:-1, 1:-1] = True
    if mask is not None:
        inner &= np.asarray(mask, bool)
    if not inner.any():
        return 0.0
    return float(cv2.Laplacian(gray, cv2.CV_64F, ksize=1)[inner].var())


def _polygon_mask(layout: Layout, points: np.ndarray, name: str, shape: tuple[int, int]) -> np.ndarray:
    import cv2

    mask = np.zeros(shape, np.uint8)
    poly = np.round(points[list(layout.subregion(name).polygon)] * 16).astype(np.int32)
    cv2.fillPoly(mask, [poly], 1, lineType=cv2.LINE_8, shift=4)
    return mask.astype(bool)


def region_masks(layout: Layout, points: np.ndarray, shape: tuple[int, int]) -> dict[str, np.ndarray]:
    """Pixel masks ``(h, w) bool`` of the regions the measurements use, for one face.

    ``eyezone_l``/``eyezone_r`` (the eye zone polygons, eyes included), ``lips`` (outer lip
    polygon minus the inner one), ``mouth`` (inside the inner lip line), ``skin`` (both cheeks),
    ``face`` (every subregion but the lips and the mouth).
    ``points (N, 2)`` px are in the coordinates of an image of ``shape = (h, w)``.
    """
    teeth = layout.teeth_subregion
    if teeth is None:
        raise ValueError(f"layout {layout.name!r} has no teeth subregion (the inner lip line)")
    mouth = _polygon_mask(layout, points, teeth.name, shape)
    masks = {name: _polygon_mask(layout, points, name, shape) for name in ("eyezone_l", "eyezone_r")}
    lips = _polygon_mask(layout, points, "lips", shape)
    masks["lips"] = lips & ~mouth
    masks["face"] = (subregion_mask(layout, points, shape[::-1]) >= 0) & ~lips & ~mouth
    masks["mouth"] = mouth
    masks["skin"] = np.logical_or(*(_polygon_mask(layout, points, n, shape) for n in SKIN_REGIONS))
    return masks


def measure_frame(image: np.ndarray, points: np.ndarray, layout: Layout) -> tuple[float, np.ndarray, float]:
    """Sharpness, region colours and teeth fraction of one frame.

    Parameters
    ----------
    image : (H, W, 3) uint8 RGB
    points : (N, 2) float
        The layout's points in this frame, px.
    layout : Layout

    Returns
    -------
    sharpness : float
        :func:`laplacian_sharpness` of the grey image over the ``face`` mask of :func:`region_masks`.
    colours : (3, 3) float64
        Mean CIE L*a*b* (L* in [0, 100]) of the :data:`OCCLUSION_REGIONS`, NaN for an empty region.
    teeth_fraction : float
        Share of the inner-mouth pixels with ``L >= median L`` and chroma ``<= median chroma`` of
        the cheeks (0 when the mouth covers no pixel).
    """
    import cv2

    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {image.shape} {image.dtype}")
    H, W = image.shape[:2]
    x0, y0, x1, y1 = face_box(points, (W, H))
    if x1 - x0 < 3 or y1 - y0 < 3:
        return 0.0, np.full((len(OCCLUSION_REGIONS), 3), np.nan), 0.0
    crop = image[y0:y1, x0:x1]
    lab = cv2.cvtColor(crop.astype(np.float32) / 255.0, cv2.COLOR_RGB2Lab).astype(np.float64)
    masks = region_masks(layout, np.asarray(points, np.float64) - (x0, y0), crop.shape[:2])
    sharp = laplacian_sharpness(luma_opencv(crop), masks["face"])
    colours = np.array([lab[masks[r]].mean(0) if masks[r].any() else np.full(3, np.nan) for r in OCCLUSION_REGIONS])
    teeth = 0.0
    if masks["mouth"].any() and masks["skin"].any():
        chroma = np.hypot(lab[..., 1], lab[..., 2])
        light = lab[..., 0] >= np.median(lab[..., 0][masks["skin"]])
        grey = chroma <= np.median(chroma[masks["skin"]])
        teeth = float((light & grey)[masks["mouth"]].mean())
    return sharp, colours, teeth


def measure_frames(
    chunks: Iterable[tuple[int, np.ndarray]], xy: np.ndarray, valid: np.ndarray, layout: Layout
) -> dict[str, np.ndarray]:
    """:func:`measure_frame` over a clip read chunk by chunk.

    Parameters
    ----------
    chunks : iterable of ``(first_frame_index, frames (B, H, W, 3) uint8)``
    xy : (T, N, 2) float
        Layout points per frame, px.
    valid : (T,) bool
        Frames with a face (the others are not measured).

    Returns
    -------
    dict
        ``sharpness (T,)``, ``colours (T, 3, 3)`` L*a*b*, ``teeth_fraction (T,)``, ``inside (T,)``
        (every point within the frame, ``-0.5 <= x <= W - 0.5``); NaN / 0 / False where not valid.
    """
    xy = np.asarray(xy, np.float64)
    valid = np.asarray(valid, bool)
    T = len(xy)
    sharp = np.full(T, np.nan)
    colours = np.full((T, len(OCCLUSION_REGIONS), 3), np.nan)
    teeth = np.zeros(T)
    inside = np.zeros(T, bool)
    for start, frames in chunks:
        H, W = frames.shape[1:3]
        for k, image in enumerate(frames):
            t = start + k
            if t >= T or not valid[t]:
                continue
            p = xy[t]
            inside[t] = bool(np.all((p >= -0.5) & (p <= (W - 0.5, H - 0.5))))
            sharp[t], colours[t], teeth[t] = measure_frame(image, p, layout)
    return {"sharpness": sharp, "colours": colours, "teeth_fraction": teeth, "inside": inside}


def classify_frames(
    *,
    valid: np.ndarray,
    inside: np.ndarray,
    angles: np.ndarray,
    sharpness: np.ndarray,
    colours: np.ndarray,
    max_yaw: float,
    max_pitch: float,
    max_roll: float,
    min_sharpness: float,
    max_colour_change: float,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The first failing check of each frame (module docstring), or :data:`KEEP`.

    Parameters
    ----------
    valid, inside : (T,) bool
    angles : (T, 3) float
        Yaw, pitch, roll in degrees (:func:`head_angles`).
    sharpness : (T,) float
        Laplacian variance over the face.
    colours : (T, R, 3) float
        Mean L*a*b* of the :data:`OCCLUSION_REGIONS`.
    max_yaw, max_pitch, max_roll : float
        Bounds on the absolute angles, degrees.
    min_sharpness : float
        Least sharpness as a fraction of the median over the frames passing the pose checks.
    max_colour_change : float
        Largest Delta E (CIE76; a*b* only where :data:`OCCLUSION_LIGHTNESS` is False) of a
        region's mean colour from its median over the frames passing the checks before it.

    Returns
    -------
    cause : (T,) int8
        Index into :data:`CAUSES`, or :data:`KEEP` (-1).
    scores : dict
        ``sharpness_rel (T,)`` (sharpness over the median) and ``colour_change (T,)`` (largest
        colour change over the regions), NaN where not computed.
    """
    valid = np.asarray(valid, bool)
    T = len(valid)
    angles = np.asarray(angles, np.float64)
    if angles.shape != (T, 3) or np.shape(inside) != (T,) or np.shape(sharpness) != (T,) or np.shape(colours)[:1] != (T,):
        raise ValueError(
            f"expected per-frame arrays for {T} frames: angles (T, 3), inside, sharpness (T,), colours (T, R, 3); "
            f"got {angles.shape}, {np.shape(inside)}, {np.shape(sharpness)}, {np.shape(colours)}"
        )
    cause = np.full(T, KEEP, np.int8)

    def reject(mask: np.ndarray, name: str) -> None:
        cause[(cause == KEEP) & mask] = CAUSES.index(name)

    reject(~valid, "no_face")
    reject(~np.asarray(inside, bool), "out_of_frame")
    bound = np.array([max_yaw, max_pitch, max_roll])
    reject((np.abs(angles) > bound).any(axis=1), "head_pose")
    sharpness = np.asarray(sharpness, np.float64)
    relative = np.full(T, np.nan)
    kept = cause == KEEP
    if kept.any():
        relative[kept] = sharpness[kept] / max(float(np.median(sharpness[kept])), 1e-12)
    reject(kept & ~(relative >= min_sharpness), "blur")
    change = np.full(T, np.nan)
    kept = cause == KEEP
    if kept.any():
        colours = np.asarray(colours, np.float64)
        median = np.nanmedian(colours[kept], axis=0)
        weight = np.ones(colours.shape[1:])
        weight[~np.array(OCCLUSION_LIGHTNESS), 0] = 0.0
        change[kept] = np.nanmax(np.linalg.norm((colours[kept] - median) * weight, axis=-1), axis=1)
    reject(kept & ~(change <= max_colour_change), "occlusion")
    return cause, {"sharpness_rel": relative, "colour_change": change}


def cause_counts(cause: np.ndarray) -> np.ndarray:
    """``(len(CAUSES),)`` int64: how many frames each cause rejected."""
    return np.bincount(np.asarray(cause, np.int64)[np.asarray(cause) != KEEP], minlength=len(CAUSES))
