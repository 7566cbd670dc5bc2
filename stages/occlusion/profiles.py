"""Image profiles across each region's contours: small warped patches that follow the landmarks.

Each region's structure is sampled on a strip laid along one of its contours (the outer lip line,
the eye outline, the brow's centre line, the lower nose outline): ``K`` positions evenly spaced by
arc length along the contour, and at each ``M`` samples along the contour's normal, at offsets
given in eye distances, plus :data:`SHIFT` more samples at each end (the model looks for the
region's structure a little off the landmarks' contour, as far as they err) (the outer eye corners' distance in the frame, so the strip scales with the
face). The strip is a ``(K, M)`` patch in the region's own coordinates: an expression that moves
the contour moves the strip with it, and what a strip shows is the image across the contour (skin
outside, lips inside; the lid margin and lashes; the dark stripe of a brow).

Two channels per sample, both invariant to the light's intensity and colour balance:
- **Weber luminance** ``Y / mean(Y) - 1`` (BT.601 luma, mean over the strip);
- **redness** ``log((R + 8) / (G + 8))`` minus its mean over the strip (lips against skin).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from stages.color import luma_float32

#: Samples along each contour.
POSITIONS = 16
#: Samples added at each end of every normal, so the structure is matched up to this many steps off.
SHIFT = 2
#: The face crop is resampled so that the eye distance spans this many pixels (sampling scale).
EYE_DISTANCE_PX = 96.0
EYE_OUTER = ("eye_l_6", "eye_r_6")
#: Points whose places relative to the eye line say the head's pose (with the region's contour:
#: the face's shape, :func:`shape`).
POSE_POINTS = ("nose_tip", "eye_l_0", "eye_r_0", *EYE_OUTER)


@dataclass(frozen=True)
class Profile:
    """The strip of one region.

    ``contour``: point names in order along the contour; ``pair``: a second contour of as many
    points averaged with the first (the brow's upper edge with its lower edge gives its centre
    line), or empty; ``closed``: the contour closes on itself (its normal points outwards: the
    orientation is taken from the clip's median outline); for an open contour the normal points
    away from the mean of the ``away`` points. ``inner``, ``outer``, ``count``: the ``M``
    offsets along the normal, evenly spaced, eye distances. ``redder``: ``(a, b)`` where the
    region must be redder inside than outside its contour whoever the performer is (the lips
    against the skin): the mean redness at offsets below ``a`` minus that above ``b`` is a
    second, template-free measure of the region's structure (:func:`redness_contrast`).
    """

    contour: tuple[str, ...]
    inner: float
    outer: float
    count: int
    closed: bool = False
    pair: tuple[str, ...] = ()
    away: tuple[str, ...] = ()
    redder: tuple[float, float] | None = None

    @property
    def offsets(self) -> np.ndarray:
        """The ``M + 2 SHIFT`` offsets sampled (eye distances)."""
        step = (self.outer - self.inner) / (self.count - 1)
        return self.inner + step * np.arange(-SHIFT, self.count + SHIFT)


def _side(side: str) -> dict[str, Profile]:
    return {
        f"eye_{side}": Profile(tuple(f"eye_{side}_{k}" for k in range(12)), 0.0, 0.1, 6, closed=True),
        f"brow_{side}": Profile(
            tuple(f"brow_{side}_{k}" for k in range(4)),
            -0.12,
            0.12,
            9,
            pair=tuple(f"brow_{side}_{k}" for k in (7, 6, 5, 4)),
            away=tuple(f"eye_{side}_{k}" for k in range(12)),
        ),
    }


PROFILES: dict[str, Profile] = {
    "mouth": Profile(tuple(f"mouth_outer_{k}" for k in range(16)), -0.05, 0.07, 7, closed=True, redder=(0.0, 0.02)),
    **_side("l"),
    **_side("r"),
    "nose": Profile(
        ("nose_ala_l", "nose_nostril_l", "nose_base", "nose_nostril_r", "nose_ala_r"),
        -0.1,
        0.06,
        9,
        away=("nose_tip", "nose_bridge_2"),
    ),
}


@dataclass(frozen=True)
class Sampler:
    """The columns of one points bundle that each region's strip needs, and the closed contours'
    orientation (+1 or -1: the sign turning the tangent into the outward normal)."""

    regions: tuple[str, ...]
    contour: tuple[np.ndarray, ...]
    pair: tuple[np.ndarray | None, ...]
    away: tuple[np.ndarray | None, ...]
    orientation: tuple[float, ...]
    eyes: np.ndarray
    pose: np.ndarray

    @property
    def shapes(self) -> dict[str, tuple[int, int]]:
        return {r: (POSITIONS, len(PROFILES[r].offsets)) for r in self.regions}


def make_sampler(names: Sequence[str], xy: np.ndarray, valid: np.ndarray, regions: Sequence[str]) -> Sampler:
    """The sampler of ``regions`` over a bundle's point ``names`` (N,); ``xy (T, N, 2)`` and
    ``valid (T,)`` give each closed contour's orientation (the sign of its median signed area,
    so that a shut eye's collapsed outline keeps the open eye's outward side)."""
    where = {str(n): i for i, n in enumerate(names)}
    contour, pair, away, orientation = [], [], [], []
    for region in regions:
        profile = PROFILES[region]
        cols = np.array([where[n] for n in profile.contour])
        contour.append(cols)
        pair.append(np.array([where[n] for n in profile.pair]) if profile.pair else None)
        away.append(np.array([where[n] for n in profile.away]) if profile.away else None)
        sign = 1.0
        if profile.closed and valid.any():
            p = xy[valid][:, cols]
            x, y = p[..., 0], p[..., 1]
            area = 0.5 * (x * np.roll(y, -1, axis=1) - y * np.roll(x, -1, axis=1)).sum(axis=1)
            sign = 1.0 if np.median(area) >= 0 else -1.0
        orientation.append(sign)
    eyes = np.array([where[n] for n in EYE_OUTER])
    pose = np.array([where[n] for n in POSE_POINTS])
    return Sampler(tuple(regions), tuple(contour), tuple(pair), tuple(away), tuple(orientation), eyes, pose)


def shape(sampler: Sampler, xy: np.ndarray, region: int) -> np.ndarray:
    """The face's shape as the region sees it: its contour's points (both contours of a paired
    one) and :data:`POSE_POINTS` in the eye line's frame (origin between the outer eye corners,
    x along the eye line, unit the eye distance), ``(F, 2 P)`` for points ``xy (F, N, 2)``."""
    cols = [sampler.contour[region], *([] if sampler.pair[region] is None else [sampler.pair[region]]), sampler.pose]
    p = xy[:, np.concatenate(cols)]
    left, right = xy[:, sampler.eyes[0]], xy[:, sampler.eyes[1]]
    axis = right - left
    scale = np.hypot(axis[:, 0], axis[:, 1])[:, None]
    along = axis / scale
    rel = p - ((left + right) / 2)[:, None]
    local = (
        np.stack([(rel * along[:, None]).sum(-1), rel[..., 1] * along[:, None, 0] - rel[..., 0] * along[:, None, 1]], axis=-1)
        / scale[..., None]
    )
    return local.reshape(len(xy), -1)


def _resample(polyline: np.ndarray, closed: bool, count: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points evenly spaced by arc length on a polyline ``(P, 2)`` and the unit tangents
    there ``(count, 2)``."""
    p = np.vstack([polyline, polyline[:1]]) if closed else polyline
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(p, axis=0).T))])
    if arc[-1] <= 1e-9:
        arc = np.linspace(0.0, 1.0, len(p))
    u = (np.arange(count) + 0.5) / count * arc[-1] if closed else np.linspace(0.0, arc[-1], count)
    q = np.stack([np.interp(u, arc, p[:, 0]), np.interp(u, arc, p[:, 1])], axis=1)
    du = 0.5 * arc[-1] / count
    ahead = np.stack(
        [
            np.interp(u + du, arc, p[:, 0], period=arc[-1] if closed else None),
            np.interp(u + du, arc, p[:, 1], period=arc[-1] if closed else None),
        ],
        axis=1,
    )
    behind = np.stack(
        [
            np.interp(u - du, arc, p[:, 0], period=arc[-1] if closed else None),
            np.interp(u - du, arc, p[:, 1], period=arc[-1] if closed else None),
        ],
        axis=1,
    )
    tangent = ahead - behind
    tangent /= np.maximum(np.hypot(tangent[:, 0], tangent[:, 1]), 1e-9)[:, None]
    return q, tangent


def sample_grid(sampler: Sampler, xy: np.ndarray) -> tuple[np.ndarray, float]:
    """Where each region's strip samples one frame: ``(S, 2)`` px (the regions' strips
    flattened in order, each ``K x M`` row-major) and the frame's eye distance (px).

    ``xy`` is the frame's points ``(N, 2)`` px.
    """
    eye = float(np.hypot(*(xy[sampler.eyes[1]] - xy[sampler.eyes[0]])))
    grids = []
    for r, region in enumerate(sampler.regions):
        profile = PROFILES[region]
        line = xy[sampler.contour[r]]
        if sampler.pair[r] is not None:
            line = (line + xy[sampler.pair[r]]) / 2
        q, tangent = _resample(line, profile.closed, POSITIONS)
        normal = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)  # tangent turned 90 degrees
        if profile.closed:
            normal *= sampler.orientation[r]
        else:
            centre = xy[sampler.away[r]].mean(axis=0)
            normal *= np.where(np.sum((q - centre) * normal, axis=1) < 0, -1.0, 1.0)[:, None]
        offsets = profile.offsets * eye
        grids.append((q[:, None, :] + offsets[None, :, None] * normal[:, None, :]).reshape(-1, 2))
    return np.concatenate(grids), eye


def sample_frame(frame: np.ndarray, grid: np.ndarray, eye: float) -> np.ndarray:
    """RGB at ``grid (S, 2)`` px of ``frame (H, W, 3)`` uint8, bilinear, after resampling the
    crop around the grid so that the eye distance spans :data:`EYE_DISTANCE_PX` (area
    averaging: the strip sees the face at one scale whatever the clip's resolution).
    Returns ``(S, 3)`` float32; samples outside the frame repeat its edge."""
    import cv2

    h, w = frame.shape[:2]
    x0, y0 = np.floor(grid.min(axis=0)).astype(int) - 2
    x1, y1 = np.ceil(grid.max(axis=0)).astype(int) + 3
    x0, y0, x1, y1 = min(max(x0, 0), w - 1), min(max(y0, 0), h - 1), max(min(x1, w), 1), max(min(y1, h), 1)
    crop = frame[y0:y1, x0:x1]  # never empty: x0 < x1, y0 < y1 after the clamps
    scale = min(1.0, EYE_DISTANCE_PX / max(eye, 1.0))
    if scale < 1.0:
        size = (max(1, round(crop.shape[1] * scale)), max(1, round(crop.shape[0] * scale)))
        crop = cv2.resize(crop, size, interpolation=cv2.INTER_AREA)
        sx, sy = size[0] / (x1 - x0), size[1] / (y1 - y0)
    else:
        sx = sy = 1.0
    # pixel centres: x_crop = (x - x0 + 0.5) * s - 0.5
    mx = ((grid[:, 0] - x0 + 0.5) * sx - 0.5).astype(np.float32)[None]
    my = ((grid[:, 1] - y0 + 0.5) * sy - 0.5).astype(np.float32)[None]
    return cv2.remap(crop, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0].astype(np.float32)


def channels(rgb: np.ndarray) -> np.ndarray:
    """The two channels of strips ``(..., K, M, 3)`` RGB: ``(..., K, M, 2)`` Weber luminance and
    mean-free redness (module doc), each over its own strip."""
    rgb = np.asarray(rgb, np.float32)
    luma = luma_float32(rgb)
    weber = luma / np.maximum(luma.mean(axis=(-2, -1), keepdims=True), 1.0) - 1.0
    red = np.log((rgb[..., 0] + 8.0) / (rgb[..., 1] + 8.0))
    red -= red.mean(axis=(-2, -1), keepdims=True)
    return np.stack([weber, red], axis=-1)


def redness_contrast(strips: np.ndarray, profile: Profile) -> np.ndarray:
    """The mean redness inside minus outside the contour (``profile.redder``) of each strip
    ``(F, K, M + 2 SHIFT, 2)`` (:func:`channels`), over its unshifted offsets: ``(F,)``."""
    offsets = profile.offsets
    inside, outside = offsets < profile.redder[0], offsets > profile.redder[1]
    middle = np.zeros(len(offsets), bool)
    middle[SHIFT : len(offsets) - SHIFT] = True
    red = np.asarray(strips, np.float64)[..., 1]
    return red[:, :, inside & middle].mean(axis=(1, 2)) - red[:, :, outside & middle].mean(axis=(1, 2))
