"""The 3D face model: mean shape of the layout's points, identities from a seed, expression controls.

Head frame (mm): x to the viewer's right, y down, z away from the camera (OpenCV camera axes for
a frontal face), origin between the eyes on the eye line. The surface is a height field
``z = depth(x, y)`` over the frontal plane; the feature points and the extra mesh vertices lie
on it. Expression controls (action-unit-like, each in [0, 1]) move the 3D feature points.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from stages.layout import Layout

# Expression controls, in the order of every `controls` array (docs/fixtures.md).
CONTROLS: tuple[str, ...] = (
    "inner_brow_raise",  # AU1
    "outer_brow_raise",  # AU2
    "brow_lower",  # AU4
    "lid_close",  # AU43 (blink)
    "squint",  # AU7
    "smile",  # AU12 + AU6 (lip corner pull, cheek raise)
    "lip_stretch",  # AU20
    "lip_pucker",  # AU18
    "jaw_drop",  # AU26/27 (mouth open)
    "upper_lip_raise",  # AU10
    "lip_corner_depress",  # AU15
    "chin_raise",  # AU17
)

# Jaw drop (AU26/27) in two phases, each a rotation of the jaw-borne points about an x-parallel
# axis (mm, head frame). Up to jaw_drop = JAW_HINGE_END the hinge phase of speech-sized openings
# (inner lips about 8% of the outer-eye-corner distance apart at its end); beyond it the wide
# opening (AU27), where the condyles glide forward: the chin swings down and forward again, the
# two phases together turning the jaw about its angle, and the upper lip stretches up off the
# upper teeth. At jaw_drop = 1 the inner lips are about half the outer-eye-corner distance apart.
JAW_PIVOT = np.array([0.0, -30.0, 70.0])  # axis of the hinge phase
JAW_MAX_DEG = 22.0  # hinge-phase degrees per unit of jaw_drop
JAW_HINGE_END = 0.5
JAW_WIDE_PIVOT = np.array([0.0, 130.0, 110.0])  # axis of the wide phase
JAW_WIDE_UPPER_LIP_MM = 4.5  # inner upper lip up at jaw_drop = 1 (at the midline)
JAW_WIDE_DEG = 18.0  # degrees added from JAW_HINGE_END to jaw_drop = 1


def _left_template() -> dict[str, tuple[float, float]]:
    """Mean-face (x, y) of the viewer's-left and midline points in mm (right side mirrors)."""
    p: dict[str, tuple[float, float]] = {}
    for i in range(17):
        t = np.pi * i / 16.0
        c, s = np.cos(t), np.sin(t)
        p[f"contour_{i}"] = (-70.0 * np.sign(c) * abs(c) ** 0.75, -4.0 + 104.0 * s**1.35)
    p["temple_l"] = (-67.0, -40.0)
    for i, x in enumerate((-50.0, -25.0, 0.0, 25.0, 50.0)):
        p[f"hairline_{i}"] = (x, -80.0 + 0.0075 * x * x)
    p["forehead_l"], p["forehead_c"] = (-28.0, -52.0), (0.0, -55.0)
    p["glabella"] = (0.0, -17.0)
    lower = [(-13.0, -17.0), (-26.0, -20.5), (-41.0, -20.5), (-55.0, -15.5)]
    upper = [(-53.0, -20.0), (-41.0, -26.5), (-26.0, -26.5), (-13.0, -23.0)]
    for i, q in enumerate(lower + upper):
        p[f"brow_l_{i}"] = q
    cx, half_w = -32.0, 14.5
    for i in range(12):
        if i <= 6:
            t = i / 6.0
            x = cx + half_w - 2 * half_w * t
            y = -6.2 * np.sin(np.pi * t) ** 0.9 + 0.8 * (1 - t) - 0.6 * t
        else:
            t = (i - 6) / 6.0
            x = cx - half_w + 2 * half_w * t
            y = 4.3 * np.sin(np.pi * t) ** 0.9 - 0.6 * (1 - t) + 0.8 * t
        p[f"eye_l_{i}"] = (x, y)
    for i, t in enumerate((0.25, 0.5, 0.75)):
        p[f"crease_l_{i}"] = (cx + half_w - 2 * half_w * t, -6.2 * np.sin(np.pi * t) - 3.8)
    p["under_eye_l"] = (-33.0, 13.0)
    p["nose_bridge_0"], p["nose_bridge_1"], p["nose_bridge_2"] = (0.0, 1.0), (0.0, 13.0), (0.0, 25.0)
    p["nose_tip"] = (0.0, 35.0)
    p["nose_side_l"] = (-8.0, 13.0)
    p["nose_alar_crease_l"] = (-15.0, 29.0)
    p["nose_ala_l"] = (-16.5, 37.0)
    p["nose_nostril_l"] = (-8.0, 41.0)
    p["nose_base"] = (0.0, 43.0)
    # outer lip line: 0 left corner, 1..7 upper left->right, 8 right corner, 9..15 lower right->left
    corner = (-25.0, 62.0)
    upper_lip = [(-19.0, 58.5), (-12.0, 55.5), (-5.5, 54.0), (0.0, 55.3)]
    lower_lip = [(-6.0, 73.0), (-13.0, 71.5), (-19.5, 67.5)]
    p["mouth_outer_0"] = corner
    for i, q in enumerate(upper_lip, start=1):
        p[f"mouth_outer_{i}"] = q
    p["mouth_outer_12"] = (0.0, 73.5)
    for i, q in zip((13, 14, 15), lower_lip):
        p[f"mouth_outer_{i}"] = q
    # inner lip line (neutral: closed): 0 left corner, 1..4 upper, 5 right corner, 6..9 lower
    p["mouth_inner_0"] = (-21.0, 62.0)
    p["mouth_inner_1"], p["mouth_inner_2"] = (-12.0, 62.0), (-4.0, 62.0)
    p["mouth_inner_9"], p["mouth_inner_8"] = (-12.0, 62.0), (-4.0, 62.0)
    p["teeth_upper_0"], p["teeth_upper_1"] = (-14.0, 62.5), (-5.0, 63.0)
    p["teeth_lower_0"], p["teeth_lower_1"] = (-13.0, 62.0), (-4.5, 61.5)
    p["nasolabial_l_0"] = (-20.0, 39.0)
    p["nasolabial_l_1"] = (-28.0, 53.0)
    p["nasolabial_l_2"] = (-32.0, 70.0)
    p["cheek_l"] = (-45.0, 28.0)
    p["lipfold_l"] = (-28.0, 81.0)
    p["chin"] = (0.0, 88.0)
    return p


def _mirror_name(name: str) -> str | None:
    """The name of the viewer's-right twin of a viewer's-left point (``*_l`` / ``*_l_k``), else None."""
    if re.search(r"_l(_|$)", name):
        return re.sub(r"_l(_|$)", r"_r\1", name)
    return None


def mean_template(layout: Layout) -> np.ndarray:
    """Mean-face frontal (x, y) of every layout point, ``(N, 2)`` mm, neutral expression."""
    left = _left_template()
    out = np.full((layout.n_points, 2), np.nan)
    for name, (x, y) in left.items():
        out[layout.index(name)] = (x, y)
        twin = None
        if name.startswith("contour_"):
            twin = f"contour_{16 - int(name.split('_')[1])}"
        elif name.startswith("mouth_outer_"):
            k = int(name.split("_")[2])
            twin = f"mouth_outer_{8 - k if k <= 8 else 24 - k}"
        elif name.startswith("mouth_inner_"):
            k = int(name.split("_")[2])
            twin = f"mouth_inner_{5 - k if k <= 5 else 15 - k}"
        elif name.startswith("hairline_"):
            twin = f"hairline_{4 - int(name.split('_')[1])}"
        elif name.startswith("teeth_"):
            kind, i = name.rsplit("_", 1)
            twin = f"{kind}_{3 - int(i)}"
        else:
            twin = _mirror_name(name)
        if twin is not None and twin in layout.point_names and twin not in left:
            out[layout.index(twin)] = (-x, y)
    missing = [layout.point_names[i] for i in np.flatnonzero(np.isnan(out[:, 0]))]
    if missing:
        raise ValueError(f"the face model has no template position for {missing[:5]}")
    return out


@dataclass(frozen=True)
class Identity:
    """One synthetic person: shape and appearance parameters drawn from a seed.

    ``offsets`` ``(N, 2)`` mm are smooth identity-specific displacements of the mean template;
    ``depth_params`` scale the height-field features; the colours are sRGB in [0, 1].
    """

    seed: int
    scale: float
    offsets: np.ndarray
    depth_params: dict[str, float]
    skin: np.ndarray
    lip: np.ndarray
    hair: np.ndarray
    iris: np.ndarray
    brow_density: float
    wrinkle_seed: int
    detail_gain: float = 1.0


SKIN_TONES = np.array([[0.96, 0.80, 0.69], [0.89, 0.69, 0.56], [0.78, 0.57, 0.44], [0.62, 0.43, 0.31], [0.45, 0.30, 0.22]])
HAIR = np.array([[0.10, 0.07, 0.05], [0.25, 0.16, 0.09], [0.45, 0.32, 0.18], [0.62, 0.48, 0.30], [0.30, 0.29, 0.28]])
IRIS = np.array([[0.30, 0.18, 0.10], [0.20, 0.35, 0.50], [0.30, 0.40, 0.25], [0.45, 0.30, 0.15]])


def make_identity(seed: int, layout: Layout) -> Identity:
    """Draw a person from ``seed`` (any integer; the same seed gives the same person)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7919]))
    base = mean_template(layout)
    names = layout.point_names
    width = rng.uniform(0.92, 1.08)
    height = rng.uniform(0.94, 1.06)
    off = base * np.array([width - 1.0, height - 1.0])

    def group(prefix: str) -> np.ndarray:
        return np.array([n.startswith(prefix) for n in names])

    def both(prefix: str) -> tuple[np.ndarray, np.ndarray]:
        return group(prefix + "_l"), group(prefix + "_r")

    eye_dx, eye_scale, eye_dy = rng.uniform(-2.5, 2.5), rng.uniform(0.9, 1.1), rng.uniform(-1.5, 1.5)
    for sign, m in zip((-1, 1), both("eye")):
        centre = base[m].mean(axis=0)
        off[m] += (base[m] - centre) * (eye_scale - 1.0) + (sign * eye_dx, eye_dy)
    for sign, m in zip((-1, 1), both("crease")):
        off[m] += (sign * eye_dx, eye_dy - rng.uniform(0.0, 1.5))
    brow_dy = rng.uniform(-3.0, 2.0)
    for m in both("brow"):
        off[m] += (0.0, brow_dy)
    nose = group("nose_")
    nose_w, nose_len = rng.uniform(0.85, 1.2), rng.uniform(-3.0, 3.0)
    off[nose] += np.stack([base[nose, 0] * (nose_w - 1.0), np.clip(base[nose, 1], 0, None) / 43.0 * nose_len], axis=1)
    mouth = group("mouth_") | group("teeth_")
    mouth_w, lip_t, mouth_dy = rng.uniform(0.88, 1.15), rng.uniform(0.8, 1.3), rng.uniform(-2.0, 3.0)
    rel = base[mouth] - (0.0, 62.0)
    off[mouth] += np.stack([rel[:, 0] * (mouth_w - 1.0), rel[:, 1] * (lip_t - 1.0) + mouth_dy], axis=1)
    jaw_w = rng.uniform(0.9, 1.1)
    scale = float(rng.uniform(0.95, 1.05))
    for i in range(3, 14):
        k = layout.index(f"contour_{i}")
        off[k, 0] += base[k, 0] * (jaw_w - 1.0) * np.sin(np.pi * i / 16)
    off += rng.normal(0.0, 0.35, size=off.shape)
    tone = rng.uniform(0, len(SKIN_TONES) - 1)
    lo = int(np.floor(tone))
    hi = min(lo + 1, len(SKIN_TONES) - 1)
    skin = SKIN_TONES[lo] * (1 - (tone - lo)) + SKIN_TONES[hi] * (tone - lo)
    lip = np.clip(skin * np.array([0.92, 0.62, 0.62]) + rng.uniform(-0.03, 0.03, 3), 0, 1)
    return Identity(
        seed=int(seed),
        scale=scale,
        offsets=off,
        depth_params={
            "nose": float(rng.uniform(0.8, 1.25)),
            "brow_ridge": float(rng.uniform(0.6, 1.4)),
            "cheekbone": float(rng.uniform(0.6, 1.4)),
            "chin": float(rng.uniform(0.7, 1.3)),
            "lips": float(rng.uniform(0.8, 1.2)),
            "jaw_a": float((72.0 * width * max(jaw_w, 1.0) + 3.0) * scale),  # the neck falls back below this jaw line
            "jaw_b": float(104.0 * height * scale),
        },
        skin=skin,
        lip=lip,
        hair=HAIR[rng.integers(len(HAIR))] * rng.uniform(0.8, 1.2),
        iris=IRIS[rng.integers(len(IRIS))],
        brow_density=float(rng.uniform(0.7, 1.0)),
        wrinkle_seed=int(rng.integers(2**31)),
        detail_gain=float(rng.uniform(0.8, 1.2)),
    )


def depth(x: np.ndarray, y: np.ndarray, params: dict[str, float] | None = None) -> np.ndarray:
    """Height field of the face surface: z (mm, away from the camera) at frontal (x, y) mm.

    An ellipsoidal head with a nose, brow ridge, eye sockets, cheekbones, lips and chin, and a
    neck that falls back below the jaw.
    """
    p = {
        "nose": 1.0,
        "brow_ridge": 1.0,
        "cheekbone": 1.0,
        "chin": 1.0,
        "lips": 1.0,
        "jaw_a": 75.0,
        "jaw_b": 104.0,
        **(params or {}),
    }
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    a, b, c, y0 = 86.0, 130.0, 95.0, 8.0
    r = np.clip(1.0 - (x / a) ** 2 - ((y - y0) / b) ** 2, 0.0, None)
    z = c * (1.0 - np.sqrt(r))
    ty = np.clip((y + 4.0) / 39.0, 0.0, 1.0)
    width = 5.5 + 9.0 * ty
    ridge = (2.0 + 20.0 * ty**1.6) * np.where(y > 35.0, np.exp(-(((y - 35.0) / 6.0) ** 2)), 1.0)
    ridge *= np.where(y < -4.0, np.exp(-(((y + 4.0) / 10.0) ** 2)), 1.0)
    z -= p["nose"] * ridge * np.exp(-((x / width) ** 2))
    for sx in (-1.0, 1.0):
        z += 7.0 * np.exp(-(((x - sx * 32.0) / 15.0) ** 2) - ((y + 1.0) / 11.0) ** 2)
        z -= p["cheekbone"] * 4.0 * np.exp(-(((x - sx * 44.0) / 14.0) ** 2) - ((y - 20.0) / 13.0) ** 2)
    z -= p["brow_ridge"] * 3.0 * np.exp(-(((y + 19.0) / 7.0) ** 2)) * np.exp(-((x / 55.0) ** 4))
    z -= p["lips"] * 5.0 * np.exp(-((x / 22.0) ** 2) - ((y - 64.0) / 10.0) ** 2)
    z -= p["chin"] * 4.0 * np.exp(-((x / 16.0) ** 2) - ((y - 92.0) / 9.0) ** 2)
    jaw = -4.0 + p["jaw_b"] * np.sqrt(np.clip(1.0 - (x / p["jaw_a"]) ** 2, 0.0, 1.0)) ** 1.35
    z += 45.0 * np.clip((y - jaw) / 22.0, 0.0, 1.0) ** 1.5
    return z


def neutral_points3d(identity: Identity, layout: Layout) -> np.ndarray:
    """The identity's neutral 3D feature points ``(N, 3)`` mm in the head frame.

    Teeth points sit 7 mm behind the lip surface (upper on the head, lower on the jaw).
    """
    xy = (mean_template(layout) + identity.offsets) * identity.scale
    z = depth(xy[:, 0], xy[:, 1], identity.depth_params)
    teeth = np.array([n.startswith("teeth_") for n in layout.point_names])
    z[teeth] += 7.0
    return np.column_stack([xy, z])


def mean_model3d(layout: Layout) -> np.ndarray:
    """The generic face model of Sec. 12.1: the mean shape's neutral 3D points ``(N, 3)`` mm."""
    xy = mean_template(layout)
    z = depth(xy[:, 0], xy[:, 1])
    teeth = np.array([n.startswith("teeth_") for n in layout.point_names])
    z[teeth] += 7.0
    return np.column_stack([xy, z])


def _jaw_weights(layout: Layout, neutral: np.ndarray, *, wide: bool = False) -> np.ndarray:
    """How much each point rides on the jaw ``(N,)`` in [0, 1] (jaw drop rotates it that much).

    ``wide``: the weights of the wide-opening phase, spread further from the lower lip so the
    skin between moving and still points stretches instead of folding: more on the mouth corners,
    nasolabial lines and cheeks, less on the lip-corner folds, and the upper lip line following
    the corners by ``|x / half mouth width| ** 1.5`` (the open mouth's oval). ``neutral`` ``(N, 3)`` mm.
    """
    corner, naso, cheek, lipfold = (0.7, (0.4, 0.7), 0.2, 0.85) if wide else (0.5, (0.2, 0.4), 0.1, 1.0)
    half_w = max(abs(neutral[layout.index("mouth_outer_0"), 0]), 1.0)
    names = layout.point_names
    jaw = np.zeros(len(names))
    for i, n in enumerate(names):
        if n.startswith("contour_"):
            k = int(n.split("_")[1])
            jaw[i] = float(np.clip((min(k, 16 - k) - 1.5) / 3.0, 0.0, 1.0))
        elif n == "chin" or n.startswith("teeth_lower"):
            jaw[i] = 1.0
        elif n in ("lipfold_l", "lipfold_r"):
            jaw[i] = lipfold
        elif n.startswith("mouth_"):
            k = int(n.rsplit("_", 1)[1])
            lower, corners = ((9, 15), (0, 8)) if n.startswith("mouth_outer") else ((6, 9), (0, 5))
            if lower[0] <= k <= lower[1]:
                jaw[i] = 1.0
            elif k in corners:
                jaw[i] = corner
            elif wide:
                jaw[i] = corner * min(abs(neutral[i, 0]) / half_w, 1.0) ** 1.5
        elif n.startswith("nasolabial_"):
            jaw[i] = {"0": 0.0, "1": naso[0], "2": naso[1]}[n[-1]]
        elif n.startswith("cheek_"):
            jaw[i] = cheek
    return jaw


def expression_points3d(neutral: np.ndarray, controls: np.ndarray, layout: Layout) -> np.ndarray:
    """Move the neutral 3D points by the expression controls.

    Parameters
    ----------
    neutral
        ``(N, 3)`` mm, the identity's neutral points (:func:`neutral_points3d`).
    controls
        ``(C,)`` values in [0, 1] in the order of :data:`CONTROLS`.

    Returns
    -------
    numpy.ndarray
        ``(N, 3)`` mm, the expression's points in the head frame.
    """
    c = dict(zip(CONTROLS, np.clip(np.asarray(controls, dtype=np.float64), 0.0, 1.0)))
    names = layout.point_names
    idx = {n: i for i, n in enumerate(names)}
    d = np.zeros_like(neutral)

    # brows (AU1, AU2, AU4)
    for i, n in enumerate(names):
        if n.startswith("brow_"):
            k = int(n[-1])
            inner = {0: 1.0, 7: 1.0, 1: 0.75, 6: 0.75, 2: 0.35, 5: 0.35, 3: 0.1, 4: 0.1}[k]
            sx = -1.0 if "_l_" in n else 1.0
            d[i] += (0.0, -9.0 * inner * c["inner_brow_raise"], 0.0)
            d[i] += (0.0, -8.0 * (1.2 - inner) * c["outer_brow_raise"], 0.0)
            d[i] += np.array((-sx * 3.5 * inner, 5.0 * (0.5 + 0.5 * inner), -1.0)) * c["brow_lower"]
        elif n.startswith("crease_"):
            d[i] += (0.0, -2.5 * c["inner_brow_raise"] - 2.5 * c["outer_brow_raise"] + 2.0 * c["brow_lower"], 0.0)
        elif n.startswith("forehead_") or n == "glabella":
            d[i] += (0.0, -3.0 * c["inner_brow_raise"] - 1.5 * c["outer_brow_raise"], 0.0)
            if n == "glabella":
                d[i] += (0.0, 2.5 * c["brow_lower"], -1.5 * c["brow_lower"])
    # eyes: lid close (AU43), squint (AU7), cheek raise by smile (AU6)
    for s in "lr":
        e = neutral[[idx[f"eye_{s}_{k}"] for k in range(12)]]
        close = c["lid_close"]
        for k in range(1, 6):
            lower_k = 12 - k
            target = 0.75 * e[lower_k] + 0.25 * e[k]
            d[idx[f"eye_{s}_{k}"]] += (target - e[k]) * close
            d[idx[f"eye_{s}_{k}"]] += (0.0, 1.8 * c["squint"] + 1.2 * c["brow_lower"], 0.0)
        for k in range(7, 12):
            d[idx[f"eye_{s}_{k}"]] += (0.0, -1.0 * close - 2.2 * c["squint"] - 1.6 * c["smile"], -0.5 * c["smile"])
        for k in range(3):
            d[idx[f"crease_{s}_{k}"]] += (0.0, 3.0 * close + 1.0 * c["squint"], 0.0)
        sx = -1.0 if s == "l" else 1.0
        d[idx[f"eye_{s}_6"]] += (-sx * 1.2 * c["squint"] - sx * 0.8 * c["smile"], -0.5 * c["smile"], 0.0)
        d[idx[f"under_eye_{s}"]] += (0.0, -3.0 * c["smile"] - 1.5 * c["squint"], -1.5 * c["smile"])
        d[idx[f"cheek_{s}"]] += (0.0, -4.5 * c["smile"], -3.0 * c["smile"])
    # mouth corners and lips
    for s, corner_o, corner_i in (("l", 0, 0), ("r", 8, 5)):
        sx = -1.0 if s == "l" else 1.0
        smile = np.array((sx * 6.0, -6.5, 3.0)) * c["smile"]
        stretch = np.array((sx * 7.0, 1.0, 1.0)) * c["lip_stretch"]
        pucker = np.array((-sx * 8.0, 0.0, -5.0)) * c["lip_pucker"]
        depress = np.array((sx * 1.0, 5.5, 0.0)) * c["lip_corner_depress"]
        corner_move = smile + stretch + pucker + depress
        d[idx[f"mouth_outer_{corner_o}"]] += corner_move
        d[idx[f"mouth_inner_{corner_i}"]] += corner_move
        d[idx[f"nasolabial_{s}_1"]] += (
            np.array((sx * 3.0, -3.5, -2.5)) * c["smile"] + np.array((0, -2.0, 0)) * c["upper_lip_raise"]
        )
        d[idx[f"nasolabial_{s}_2"]] += (
            np.array((sx * 4.5, -4.0, -2.0)) * c["smile"] + np.array((sx * 3.0, 0.5, 0)) * c["lip_stretch"]
        )
        d[idx[f"nasolabial_{s}_0"]] += (
            np.array((sx * 1.0, -1.5, -1.0)) * c["smile"] + np.array((0, -1.8, 0)) * c["upper_lip_raise"]
        )
        d[idx[f"nose_ala_{s}"]] += (
            np.array((sx * 0.8, -1.5, 0.0)) * c["upper_lip_raise"] + np.array((sx * 0.8, -0.5, 0)) * c["smile"]
        )
        d[idx[f"nose_alar_crease_{s}"]] += np.array((sx * 0.6, -1.2, 0.0)) * c["upper_lip_raise"]
        d[idx[f"lipfold_{s}"]] += (
            np.array((sx * 3.0, -2.5, -1.0)) * c["smile"] + np.array((sx * 1.0, 3.0, 0.0)) * c["lip_corner_depress"]
        )
        d[idx[f"lipfold_{s}"]] += np.array((-sx * 3.0, 0.0, -1.0)) * c["lip_pucker"]
    # points along the lip lines follow the corners by their distance from the midline
    half_w = max(abs(neutral[idx["mouth_outer_0"], 0]), 1.0)
    for i, n in enumerate(names):
        if not n.startswith("mouth_") or n in ("mouth_outer_0", "mouth_outer_8", "mouth_inner_0", "mouth_inner_5"):
            continue
        k = int(n.rsplit("_", 1)[1])
        upper = (1 <= k <= 7) if n.startswith("mouth_outer") else (1 <= k <= 4)
        rel = neutral[i, 0] / half_w
        side = idx["mouth_outer_0"] if rel < 0 else idx["mouth_outer_8"]
        w_corner = abs(rel) ** 1.5
        d[i] += d[side] * w_corner * np.array((1.0, 1.0, 1.0))
        mid = 1.0 - abs(rel)
        outer = n.startswith("mouth_outer")
        d[i] += (0.0, (-1.0 if upper else 1.0) * 2.5 * mid * c["lip_pucker"], -5.0 * mid * c["lip_pucker"])
        d[i] += (0.0, (1.0 if upper else -1.0) * (1.2 if outer else 0.3) * c["lip_stretch"], 0.0)
        if upper:
            d[i] += (0.0, -(3.0 if outer else 4.5) * (0.4 + 0.6 * mid) * c["upper_lip_raise"], -1.0 * c["upper_lip_raise"])
        else:
            d[i] += (0.0, -(2.0 if outer else 1.0) * mid * c["chin_raise"], -1.5 * mid * c["chin_raise"])
            if not outer:
                d[i] += (0.0, -0.8 * mid * c["smile"], 0.0)
    d[idx["chin"]] += (0.0, -2.5 * c["chin_raise"], -2.0 * c["chin_raise"])
    for s in "lr":
        d[idx[f"lipfold_{s}"]] += (0.0, -1.5 * c["chin_raise"], 0.0)
    d[idx["nose_base"]] += (0.0, -0.8 * c["upper_lip_raise"], 0.0)
    out = neutral + d
    # jaw drop: rotate the jaw-borne points about the jaw axes, weighted by membership
    angle = np.deg2rad(JAW_MAX_DEG * min(c["jaw_drop"], JAW_HINGE_END))
    if angle > 0:
        out = _rotate_x(out, JAW_PIVOT, angle * _jaw_weights(layout, neutral))
    if c["jaw_drop"] > JAW_HINGE_END:
        wide = (c["jaw_drop"] - JAW_HINGE_END) / (1.0 - JAW_HINGE_END)
        out = _rotate_x(out, JAW_WIDE_PIVOT, np.deg2rad(JAW_WIDE_DEG * wide) * _jaw_weights(layout, neutral, wide=True))
        for k in range(1, 5):
            i = idx[f"mouth_inner_{k}"]
            out[i, 1] -= JAW_WIDE_UPPER_LIP_MM * wide * (1.0 - abs(neutral[i, 0]) / half_w)
    return out


def _rotate_x(points: np.ndarray, pivot: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotate ``points`` ``(N, 3)`` mm about the x-parallel axis through ``pivot`` by ``angle``
    ``(N,)`` radians each (positive: a point in front of the axis moves down, +y)."""
    rel = points - pivot
    ca, sa = np.cos(angle), np.sin(angle)
    y = ca * rel[:, 1] - sa * rel[:, 2]
    z = sa * rel[:, 1] + ca * rel[:, 2]
    return np.column_stack([points[:, 0], y + pivot[1], z + pivot[2]])
