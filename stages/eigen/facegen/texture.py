"""The face texture, drawn in texture space (the face's own frame), and its expression details.

The base texture holds skin with fine grain and blotches (so correlation trackers have texture to
lock onto), hair above the hairline, brows, lips, lash lines, nostrils. Expression details are
separate darkening maps (forehead lines, glabella furrows, crow's feet, nasolabial folds,
lip-corner folds, chin folds, lid creases); per frame each is weighted by a strength measured from
the local deformation of the 3D feature points (:func:`detail_strengths`), so the details follow
the geometry the way real wrinkles do, and no warp of the neutral image can produce them.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from stages.layout import Layout

from .face import Identity
from .mesh import FaceMesh

U0, V0, U1, V1 = -106.0, -152.0, 106.0, 168.0  # texture-space extent (mm)
SHIFT = 4

DETAILS: tuple[str, ...] = (
    "forehead_lines",
    "glabella_furrows",
    "crows_feet_l",
    "crows_feet_r",
    "nasolabial_l",
    "nasolabial_r",
    "lip_corner_l",
    "lip_corner_r",
    "chin_folds",
    "lid_crease_l",
    "lid_crease_r",
)


@dataclass(frozen=True)
class Texture:
    """Base colour ``(Ht, Wt, 3)`` float32 sRGB in [0, 1] at ``ppm`` pixels per mm; detail maps
    as ``{name: (y0, x0, crop (h, w) float32)}`` darkening fractions (negative = highlight)."""

    ppm: float
    base: np.ndarray
    details: dict[str, tuple[int, int, np.ndarray]]

    def to_px(self, uv: np.ndarray) -> np.ndarray:
        """Texture-space mm ``(..., 2)`` to texture pixel coordinates."""
        return (np.asarray(uv) - (U0, V0)) * self.ppm


def _value_noise(rng: np.random.Generator, shape: tuple[int, int], cell_px: float) -> np.ndarray:
    """Smooth noise with features of about ``cell_px`` pixels, zero mean, unit-ish amplitude."""
    h, w = shape
    gh, gw = int(h / cell_px) + 3, int(w / cell_px) + 3
    g = rng.standard_normal((gh, gw)).astype(np.float32)
    big = cv2.resize(g, (int(gw * cell_px), int(gh * cell_px)), interpolation=cv2.INTER_CUBIC)
    return big[:h, :w]


def _fixed(px: np.ndarray) -> np.ndarray:
    return np.round(np.asarray(px) * (1 << SHIFT)).astype(np.int32).reshape(-1, 1, 2)


def _mask(shape: tuple[int, int], polys: list[np.ndarray], blur_px: float) -> np.ndarray:
    m = np.zeros(shape, np.float32)
    cv2.fillPoly(m, [_fixed(p) for p in polys], 1.0, lineType=cv2.LINE_AA, shift=SHIFT)
    if blur_px > 0:
        m = cv2.GaussianBlur(m, (0, 0), blur_px)
    return m


def _blend(img: np.ndarray, mask: np.ndarray, colour: np.ndarray) -> None:
    img *= 1.0 - mask[..., None]
    img += mask[..., None] * colour


def _smooth_curve(pts: np.ndarray, n: int = 24) -> np.ndarray:
    """Catmull-Rom-like resampling of a polyline ``(K, 2)`` into ``(n, 2)`` (piecewise cubic)."""
    pts = np.asarray(pts, dtype=np.float64)
    t = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    s = np.linspace(0.0, t[-1], n)
    return (
        np.column_stack([np.interp(s, t, pts[:, 0]), np.interp(s, t, pts[:, 1])])
        if len(pts) < 3
        else np.column_stack([np.polyval(np.polyfit(t, pts[:, k], min(3, len(pts) - 1)), s) for k in range(2)])
    )


def build_texture(identity: Identity, layout: Layout, mesh: FaceMesh, *, ppm: float) -> Texture:
    """Draw the base texture and the detail maps of one identity at ``ppm`` pixels per mm."""
    rng = np.random.default_rng(np.random.SeedSequence([identity.seed, 104729]))
    w, h = int(round((U1 - U0) * ppm)), int(round((V1 - V0) * ppm))
    shape = (h, w)
    uv = mesh.feature_uv
    px = (uv - (U0, V0)) * ppm

    def P(name: str) -> np.ndarray:
        return px[layout.index(name)]

    def ring(prefix: str, count: int) -> np.ndarray:
        return np.array([P(f"{prefix}_{k}") for k in range(count)])

    # skin: tone, low-frequency blotches, pores/grain (resolution-independent cell sizes in mm)
    img = np.empty((h, w, 3), np.float32)
    img[:] = identity.skin
    blotch = 0.035 * _value_noise(rng, shape, 9.0 * ppm) + 0.02 * _value_noise(rng, shape, 3.0 * ppm)
    grain = 0.05 * _value_noise(rng, shape, max(0.6 * ppm, 1.0))
    if 0.6 * ppm < 1.5:
        grain = cv2.GaussianBlur(grain, (0, 0), 0.5)
    img *= (1.0 + blotch + grain)[..., None]
    red = np.zeros(shape, np.float32)
    for s in "lr":
        c = P(f"cheek_{s}")
        cv2.circle(red, tuple(int(v) for v in c), int(14 * ppm), 1.0, -1)
    red = cv2.GaussianBlur(red, (0, 0), 7 * ppm)
    img[..., 1:] *= (1.0 - 0.06 * red)[..., None]
    # shadow under the jaw (neck)
    jaw = ring("contour", 17)
    below = np.zeros(shape, np.float32)
    poly = np.vstack([jaw[3:14], [[jaw[13, 0], h + 10], [jaw[3, 0], h + 10]]])
    cv2.fillPoly(below, [_fixed(poly)], 1.0, lineType=cv2.LINE_AA, shift=SHIFT)
    below = cv2.GaussianBlur(below, (0, 0), 4 * ppm)
    img *= (1.0 - 0.22 * below)[..., None]
    # hair: everything above the hairline, and down the sides of the head over the ears
    hl = np.array([P("temple_l")] + [P(f"hairline_{k}") for k in range(5)] + [P("temple_r")])
    low = P("contour_3")[1] + 8 * ppm
    left = np.array(
        [
            [-10, low],
            [P("contour_3")[0] - 12 * ppm, low],
            [P("contour_1")[0] - 7 * ppm, P("contour_1")[1]],
            [P("contour_0")[0] - 4 * ppm, P("contour_0")[1]],
        ]
    )
    right = np.array(
        [
            [P("contour_16")[0] + 4 * ppm, P("contour_16")[1]],
            [P("contour_15")[0] + 7 * ppm, P("contour_15")[1]],
            [P("contour_13")[0] + 12 * ppm, low],
            [w + 10, low],
        ]
    )
    hair_poly = np.vstack([left, _smooth_curve(hl, 40), right, [[w + 10, -10], [-10, -10]]])
    hair = _mask(shape, [hair_poly], 1.2 * ppm)
    streak = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), sigmaX=0.4 * ppm, sigmaY=5 * ppm)
    streak /= max(float(streak.std()), 1e-6)
    hair_col = np.clip(identity.hair[None, None, :] * (1.0 + 0.25 * streak[..., None]), 0, 1)
    img = img * (1.0 - hair[..., None]) + hair[..., None] * hair_col
    # brows: a soft patch plus short hair strokes along the brow
    brow_col = np.clip(identity.hair * 0.8, 0, 1)
    for s in "lr":
        b = ring(f"brow_{s}", 8)
        patch = _mask(shape, [b], 0.8 * ppm) * 0.55 * identity.brow_density
        strokes = np.zeros(shape, np.float32)
        lower, upper = _smooth_curve(b[:4], 20), _smooth_curve(b[4:][::-1], 20)
        outward = (lower[-1] - lower[0]) / (np.linalg.norm(lower[-1] - lower[0]) + 1e-9)
        d = outward * 3.2 * ppm + (0, -1.2 * ppm)
        for _ in range(int(70 * identity.brow_density)):
            k = int(rng.uniform(0, 1) * 19)
            start = lower[k] + rng.uniform(0.1, 0.9) * (upper[k] - lower[k])
            cv2.line(
                strokes,
                tuple(_fixed(start)[0, 0]),
                tuple(_fixed(start + d)[0, 0]),
                0.8,
                max(1, int(0.35 * ppm)),
                cv2.LINE_AA,
                SHIFT,
            )
        a = np.clip(patch + strokes * _mask(shape, [b], 0.5 * ppm), 0, 0.95)
        _blend(img, a, brow_col)
    # lips: between the outer and inner lip lines, with vertical grain, darker towards the inside
    outer = ring("mouth_outer", 16)
    inner = ring("mouth_inner", 10)
    lips = _mask(shape, [outer], 0.35 * ppm)
    lip_grain = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), sigmaX=0.3 * ppm, sigmaY=1.2 * ppm)
    lip_col = np.clip(identity.lip[None, None, :] * (1.0 + 0.06 * lip_grain[..., None] / max(float(lip_grain.std()), 1e-6)), 0, 1)
    img = img * (1.0 - lips[..., None]) + lips[..., None] * lip_col
    edge = np.zeros(shape, np.float32)
    cv2.polylines(edge, [_fixed(inner)], True, 1.0, max(1, int(1.2 * ppm)), cv2.LINE_AA, SHIFT)
    img *= (1.0 - 0.35 * cv2.GaussianBlur(edge, (0, 0), 0.6 * ppm))[..., None]
    # eyes: lash line on the upper lid, thin lower lid line, pinkish lid skin
    for s in "lr":
        e = ring(f"eye_{s}", 12)
        lid = _mask(shape, [np.vstack([e[:7], ring(f"crease_{s}", 3)[::-1]])], 1.2 * ppm)
        img[..., 0] *= 1.0 + 0.03 * lid
        img[..., 1:] *= (1.0 - 0.06 * lid)[..., None]
        lash = np.zeros(shape, np.float32)
        cv2.polylines(lash, [_fixed(e[:7])], False, 1.0, max(1, int(1.1 * ppm)), cv2.LINE_AA, SHIFT)
        cv2.polylines(lash, [_fixed(np.vstack([e[6:], e[:1]]))], False, 0.35, max(1, int(0.5 * ppm)), cv2.LINE_AA, SHIFT)
        _blend(img, np.clip(cv2.GaussianBlur(lash, (0, 0), 0.3 * ppm), 0, 1) * 0.9, np.array([0.08, 0.05, 0.04]))
    # nostrils
    for s in "lr":
        a, n = P(f"nose_ala_{s}"), P(f"nose_nostril_{s}")
        c = 0.45 * a + 0.55 * n + (0, -0.6 * ppm)
        m = np.zeros(shape, np.float32)
        cv2.ellipse(
            m,
            tuple(int(v) for v in c),
            (int(3.2 * ppm), int(1.6 * ppm)),
            15.0 if s == "r" else -15.0,
            0,
            360,
            1.0,
            -1,
            cv2.LINE_AA,
        )
        _blend(img, cv2.GaussianBlur(m, (0, 0), 0.4 * ppm) * 0.8, np.array([0.18, 0.08, 0.07]))
    # nose and eye-socket shading painted in (ambient occlusion the Lambert term lacks)
    ao = np.zeros(shape, np.float32)
    for s in "lr":
        side = np.array([P(f"nose_side_{s}"), P(f"nose_alar_crease_{s}")])
        cv2.line(ao, tuple(_fixed(side[0])[0, 0]), tuple(_fixed(side[1])[0, 0]), 1.0, max(1, int(4 * ppm)), cv2.LINE_AA, SHIFT)
        inner_corner = 0.5 * (P(f"eye_{s}_0") + P(f"brow_{s}_0"))
        cv2.circle(ao, tuple(int(v) for v in inner_corner), int(5 * ppm), 0.8, -1, cv2.LINE_AA)
    ao = cv2.GaussianBlur(ao, (0, 0), 2.0 * ppm)
    ridge = np.zeros(shape, np.float32)
    cv2.line(
        ridge,
        tuple(_fixed(P("nose_bridge_1"))[0, 0]),
        tuple(_fixed(P("nose_tip"))[0, 0]),
        1.0,
        max(1, int(2.5 * ppm)),
        cv2.LINE_AA,
        SHIFT,
    )
    ridge = cv2.GaussianBlur(ridge, (0, 0), 1.5 * ppm)
    img *= (1.0 - 0.16 * ao + 0.07 * ridge)[..., None]
    details = _detail_maps(identity, layout, px, shape, ppm, rng)
    return Texture(ppm=ppm, base=np.clip(img, 0, 1).astype(np.float32), details=details)


def _line_map(
    shape: tuple[int, int],
    curves: list[np.ndarray],
    ppm: float,
    *,
    width_mm: float,
    depth: float,
    highlight: tuple[float, float] = (0.0, 0.0),
) -> tuple[int, int, np.ndarray]:
    """Draw wrinkle curves (pixel polylines) as a darkening map cropped to their bounding box.

    A wrinkle is a dark groove of width ``width_mm``; ``highlight = (dx_mm, dy_mm)`` adds a lit
    ridge offset from it.
    """
    allp = np.vstack(curves)
    pad = int(4 * ppm + 4)
    x0, y0 = max(int(allp[:, 0].min()) - pad, 0), max(int(allp[:, 1].min()) - pad, 0)
    x1, y1 = min(int(allp[:, 0].max()) + pad, shape[1]), min(int(allp[:, 1].max()) + pad, shape[0])
    crop = np.zeros((y1 - y0, x1 - x0), np.float32)
    lit = np.zeros_like(crop)
    for c in curves:
        n = len(c)
        taper = np.sin(np.linspace(0, np.pi, n)) ** 0.7
        for k in range(n - 1):
            a, b = c[k] - (x0, y0), c[k + 1] - (x0, y0)
            t = float(0.5 * (taper[k] + taper[k + 1]))
            cv2.line(
                crop,
                tuple(_fixed(a)[0, 0]),
                tuple(_fixed(b)[0, 0]),
                t,
                max(1, int(round(width_mm * ppm * 0.6))),
                cv2.LINE_AA,
                SHIFT,
            )
            if highlight != (0.0, 0.0):
                off = np.array(highlight) * ppm
                cv2.line(
                    lit,
                    tuple(_fixed(a + off)[0, 0]),
                    tuple(_fixed(b + off)[0, 0]),
                    t,
                    max(1, int(round(width_mm * ppm))),
                    cv2.LINE_AA,
                    SHIFT,
                )
    sigma = max(0.35 * width_mm * ppm, 0.5)
    crop = cv2.GaussianBlur(crop, (0, 0), sigma) * depth
    if highlight != (0.0, 0.0):
        crop -= cv2.GaussianBlur(lit, (0, 0), sigma * 1.5) * depth * 0.35
    return y0, x0, crop


def _detail_maps(
    identity: Identity, layout: Layout, px: np.ndarray, shape: tuple[int, int], ppm: float, rng: np.random.Generator
) -> dict[str, tuple[int, int, np.ndarray]]:
    """The expression-detail darkening maps of one identity (its wrinkle pattern)."""

    def P(name: str) -> np.ndarray:
        return px[layout.index(name)]

    g = identity.detail_gain
    out: dict[str, tuple[int, int, np.ndarray]] = {}
    # forehead: 3-5 wavy horizontal lines between the brows and the hairline
    top = min(P("hairline_1")[1], P("hairline_3")[1])
    bottom = max(P("brow_l_5")[1], P("brow_r_5")[1])
    curves = []
    n = int(rng.integers(3, 6))
    for k in range(n):
        y = bottom + (top - bottom) * (0.18 + 0.62 * (k + rng.uniform(-0.2, 0.2)) / max(n - 1, 1))
        half = (30.0 + rng.uniform(-6, 8) - 4 * k) * ppm
        xs = np.linspace(-half, half, 40) + P("glabella")[0] + rng.uniform(-3, 3) * ppm
        phase, amp = rng.uniform(0, 2 * np.pi), rng.uniform(0.6, 1.6) * ppm
        ys = y + amp * np.sin(xs / (rng.uniform(14, 24) * ppm) + phase) + 0.0025 * (xs - P("glabella")[0]) ** 2 / ppm
        curves.append(np.column_stack([xs, ys]))
    out["forehead_lines"] = _line_map(shape, curves, ppm, width_mm=0.9, depth=0.30 * g, highlight=(0.0, -1.0))
    # glabella: two vertical furrows between the brows and a short horizontal one at the nasal root
    g0 = P("glabella")
    curves = []
    for sx in (-1.0, 1.0):
        x = g0[0] + sx * rng.uniform(3.5, 5.5) * ppm
        ys = np.linspace(g0[1] - 9 * ppm, g0[1] + 6 * ppm, 12)
        curves.append(np.column_stack([x + sx * 0.04 * (ys - ys[0]), ys]))
    curves.append(
        np.column_stack([np.linspace(g0[0] - 5 * ppm, g0[0] + 5 * ppm, 8), np.full(8, (g0[1] + P("nose_bridge_0")[1]) / 2)])
    )
    out["glabella_furrows"] = _line_map(shape, curves, ppm, width_mm=1.0, depth=0.32 * g, highlight=(1.0, 0.0))
    for s, sx in (("l", -1.0), ("r", 1.0)):
        corner = P(f"eye_{s}_6")
        curves = []
        for ang in np.deg2rad(np.sort(rng.uniform(-40, 45, size=int(rng.integers(3, 5))))):
            start = corner + np.array([sx * 3.0 * ppm, 0.0])
            d = np.array([sx * np.cos(ang), np.sin(ang)])
            L = rng.uniform(7, 12) * ppm
            pts = start + np.outer(np.linspace(0, 1, 10), d * L)
            pts[:, 1] += np.linspace(0, 1, 10) ** 2 * 1.0 * ppm
            curves.append(pts)
        under = P(f"under_eye_{s}")
        e9 = P(f"eye_{s}_9")
        mid = 0.55 * e9 + 0.45 * under
        curves.append(
            np.column_stack(
                [np.linspace(mid[0] - 8 * ppm, mid[0] + 8 * ppm, 12), mid[1] + 1.2 * ppm * np.sin(np.linspace(0, np.pi, 12))]
            )
        )
        out[f"crows_feet_{s}"] = _line_map(shape, curves, ppm, width_mm=0.7, depth=0.30 * g)
        # nasolabial fold: just lateral of the nasolabial line, from the nose wing past the mouth corner
        pts = np.array([P(f"nasolabial_{s}_0"), P(f"nasolabial_{s}_1"), P(f"nasolabial_{s}_2")])
        pts = pts + np.array([sx * 2.0 * ppm, 0.0])
        pts[-1] += (sx * 1.0 * ppm, 3.0 * ppm)
        out[f"nasolabial_{s}"] = _line_map(
            shape, [_smooth_curve(pts, 30)], ppm, width_mm=2.0, depth=0.30 * g, highlight=(sx * 2.2, 0.0)
        )
        corner_m = P("mouth_outer_0" if s == "l" else "mouth_outer_8")
        lf = P(f"lipfold_{s}")
        pts = np.array(
            [corner_m + (sx * 1.5 * ppm, 1.5 * ppm), 0.5 * (corner_m + lf) + (sx * 1.5 * ppm, 0.0), lf + (0.0, 4 * ppm)]
        )
        out[f"lip_corner_{s}"] = _line_map(
            shape, [_smooth_curve(pts, 16)], ppm, width_mm=1.3, depth=0.32 * g, highlight=(sx * 1.5, 0.0)
        )
        cr = np.array(
            [
                P(f"eye_{s}_0") * 0.7 + P(f"crease_{s}_0") * 0.3,
                P(f"crease_{s}_0"),
                P(f"crease_{s}_1"),
                P(f"crease_{s}_2"),
                P(f"eye_{s}_6") * 0.6 + P(f"crease_{s}_2") * 0.4,
            ]
        )
        out[f"lid_crease_{s}"] = _line_map(
            shape, [_smooth_curve(cr, 20)], ppm, width_mm=0.8, depth=0.45 * g, highlight=(0.0, -0.8)
        )
    # chin: mentolabial sulcus and dimpling around the chin point
    lo = P("mouth_outer_12")
    ch = P("chin")
    y = 0.45 * lo[1] + 0.55 * ch[1]
    xs = np.linspace(lo[0] - 11 * ppm, lo[0] + 11 * ppm, 20)
    curve = np.column_stack([xs, y - 0.012 * (xs - lo[0]) ** 2 / ppm])
    y0, x0, crop = _line_map(shape, [curve], ppm, width_mm=1.6, depth=0.28 * g, highlight=(0.0, 1.6))
    dimple = np.zeros(shape, np.float32)
    for _ in range(14):
        c = ch + rng.normal(0, 4.0 * ppm, 2)
        cv2.circle(dimple, tuple(int(v) for v in c), max(1, int(rng.uniform(0.6, 1.3) * ppm)), 1.0, -1)
    dimple = cv2.GaussianBlur(dimple, (0, 0), 0.8 * ppm) * 0.22 * g
    yy0, yy1 = min(y0, int(ch[1] - 14 * ppm)), max(y0 + crop.shape[0], int(ch[1] + 14 * ppm))
    xx0, xx1 = min(x0, int(ch[0] - 14 * ppm)), max(x0 + crop.shape[1], int(ch[0] + 14 * ppm))
    yy0, xx0 = max(yy0, 0), max(xx0, 0)
    yy1, xx1 = min(yy1, shape[0]), min(xx1, shape[1])
    merged = dimple[yy0:yy1, xx0:xx1].copy()
    merged[y0 - yy0 : y0 - yy0 + crop.shape[0], x0 - xx0 : x0 - xx0 + crop.shape[1]] += crop
    out["chin_folds"] = (yy0, xx0, merged)
    return out


def detail_strengths(neutral: np.ndarray, points: np.ndarray, layout: Layout) -> dict[str, float]:
    """Strength in [0, 1] of each expression detail, measured from the local deformation.

    Parameters
    ----------
    neutral, points
        ``(N, 3)`` mm head-frame feature points of the identity's neutral face and of the
        expression. Only geometry is used (never the controls), so a detail appears whenever
        the skin is compressed the way that produces it.
    """
    idx = layout.index

    def y_up(name: str) -> float:
        return float(neutral[idx(name), 1] - points[idx(name), 1])

    def dist(a: str, b: str, pts: np.ndarray) -> float:
        return float(np.linalg.norm(pts[idx(a)] - pts[idx(b)]))

    brow_up = np.mean([y_up(f"brow_{s}_{k}") for s in "lr" for k in (4, 5, 6, 7)])
    out = {"forehead_lines": brow_up / 5.0}
    inner_gap = dist("brow_l_0", "brow_r_0", neutral) - dist("brow_l_0", "brow_r_0", points)
    brow_down = -np.mean([y_up(f"brow_{s}_{k}") for s in "lr" for k in (0, 7)])
    out["glabella_furrows"] = inner_gap / 4.0 + brow_down / 6.0
    for s, corner in (("l", "mouth_outer_0"), ("r", "mouth_outer_8")):
        out[f"crows_feet_{s}"] = (y_up(f"under_eye_{s}") + y_up(f"cheek_{s}")) / 5.0
        shorter = dist(corner, f"nose_ala_{s}", neutral) - dist(corner, f"nose_ala_{s}", points)
        out[f"nasolabial_{s}"] = 0.2 + shorter / 6.0 + y_up(f"nasolabial_{s}_0") / 3.0
        out[f"lip_corner_{s}"] = (
            -y_up(corner) / 4.0 + (dist(corner, f"lipfold_{s}", neutral) - dist(corner, f"lipfold_{s}", points)) / 4.0
        )
        gap = dist(f"crease_{s}_1", f"eye_{s}_3", neutral) - dist(f"crease_{s}_1", f"eye_{s}_3", points)
        out[f"lid_crease_{s}"] = 0.45 + gap / 2.5
    width = dist("mouth_outer_0", "mouth_outer_8", neutral) - dist("mouth_outer_0", "mouth_outer_8", points)
    out["chin_folds"] = (dist("mouth_outer_12", "chin", neutral) - dist("mouth_outer_12", "chin", points)) / 2.5 + width / 10.0
    return {k: float(np.clip(v, 0.0, 1.0)) for k, v in out.items()}


def frame_texture(tex: Texture, strengths: dict[str, float]) -> np.ndarray:
    """The texture of one expression: base colour darkened by the weighted detail maps, ``(Ht, Wt, 3)``."""
    factor = np.ones(tex.base.shape[:2], np.float32)
    for name, (y0, x0, crop) in tex.details.items():
        s = strengths.get(name, 0.0)
        if s > 1e-3:
            factor[y0 : y0 + crop.shape[0], x0 : x0 + crop.shape[1]] -= s * crop
    return tex.base * factor[..., None]
