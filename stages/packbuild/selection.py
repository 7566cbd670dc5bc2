"""Which usable frames become the pack's neutral, standard, examples, teeth examples and captured
geometries (paper Sec. 5.2, 6, 8, 10, 14).

Every frame's layout points are mapped into the pack's image by the least-squares 2D similarity
(eq. 8-9, :func:`stages.geometry.compensate.fit_similarity`) of its stable points (eye corners,
nose tip and base: :data:`stages.geometry.mapping.NORMALIZATION_POINTS`) onto the neutral's, then
by one more similarity that puts the neutral upright and the clip's faces centred in the pack's
image (:func:`canvas_similarity`); images and points are written that way, and by default the
geometries are compared so. Given the landmarker's depth they are compared with the head's
rotation removed in 3D instead: :func:`stages.geometry.rigid3d.compensate_rigid3d` (3D similarity
of the skull's points to the neutral's) gives each frame's displacements in the neutral's frame,
so a nod or a turn within the pose bound does not read as an expression. (Measured on real clips,
docs/packbuild.md: the 2D comparison reenacts better, since the synthesis itself works on 2D
geometry and examples spread over it, nods included, cover the test frames' geometries better.)
Distances are RMS point distances in the pack's pixels.

Sec. 14 asks for example expressions "sufficiently different from each other while covering all
captured expressions". That is the k-center problem; :func:`k_center` is the greedy 2-approximation
(Gonzalez 1985): start from the neutral, repeatedly add the frame farthest from the chosen ones.
After ``k`` picks the *coverage radius* — the largest distance of any candidate frame to its nearest
chosen one — is at most twice the optimum, and no two chosen frames are closer than it. The 30-40
captured geometries of Sec. 10 continue the same sequence from the examples (so they include
them).

Distance alone does not make a pack that shows what a performer will do: a wink or a frown held
for a few frames is close to the neutral in RMS terms and easily left out, and the pack then cannot
show shut eyes or a furrow however the geometry moves. So the k-center sequence starts from the
neutral and one frame per *expression state* the footage shows (:data:`STATE_PRIORITY`, the most
extreme frame of each: :mod:`stages.geometry.states`), then continues by distance. The neutral
has both eyes open and, when the footage ever seals them, the lips sealed; the standard image
(mouth open widest, Sec. 8) has both eyes open: never a blink or a wink.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from stages.geometry.compensate import apply_similarity, fit_similarity
from stages.geometry.mapping import NORMALIZATION_POINTS
from stages.geometry.rigid3d import RIGID_POINTS, choose_reference, compensate_rigid3d
from stages.geometry.signals import EYE_OUTER, expression_signals
from stages.geometry.states import SEALED_GAP, STATES, state_signals, state_values
from stages.layout import Layout

#: The states whose most extreme frame seeds the examples, most wanted first (a blink before each
#: eye alone: a frame with both eyes shut covers both).
STATE_PRIORITY = (
    "eye_l_shut",
    "eye_r_shut",
    "jaw_open",
    "smile",
    "brow_furrow",
    "brow_raise",
    "pucker",
    "lips_pressed",
    "eye_l_wide",
    "eye_r_wide",
    "eye_l_squint",
    "eye_r_squint",
)
EYES_OPEN_FRACTION = 0.7  # of each eye's open level (90th percentile): the neutral's and standard's eyes


def compose_similarity(outer: np.ndarray, inner: np.ndarray) -> np.ndarray:
    """``(4,)`` or ``(T, 4)`` parameters of ``outer(inner(x))`` for similarities ``(a, b, tx, ty)``
    of eq. 8 (``x -> [[a, -b], [b, a]] x + t``; in complex numbers ``z -> c z + t``, ``c = a + ib``)."""
    outer, inner = np.asarray(outer, np.float64), np.asarray(inner, np.float64)
    c_o = outer[..., 0] + 1j * outer[..., 1]
    c_i = inner[..., 0] + 1j * inner[..., 1]
    t = c_o * (inner[..., 2] + 1j * inner[..., 3]) + outer[..., 2] + 1j * outer[..., 3]
    c = c_o * c_i
    return np.stack(np.broadcast_arrays(c.real, c.imag, t.real, t.imag), axis=-1)


def stable_columns(layout: Layout) -> list[int]:
    """Rows of the stable points the geometries are aligned on (eye corners, nose tip and base)."""
    return list(layout.indices(NORMALIZATION_POINTS))


def align_to_reference(xy: np.ndarray, valid: np.ndarray, reference: np.ndarray, columns: list[int]) -> np.ndarray:
    """Per frame, the similarity (eq. 9) mapping the frame's stable points onto the reference's.

    Parameters
    ----------
    xy : (T, N, 2) float, px
    valid : (T,) bool
        Frames to fit; the others get the identity ``(1, 0, 0, 0)``.
    reference : (N, 2) float, px
    columns : list of int
        The stable points' rows.

    Returns
    -------
    (T, 4) float64 ``(a, b, tx, ty)``, frame -> reference.
    """
    xy = np.asarray(xy, np.float64)
    out = np.tile([1.0, 0.0, 0.0, 0.0], (len(xy), 1))
    for t in np.flatnonzero(valid):
        out[t] = fit_similarity(xy[t, columns], reference[columns])
    return out


#: Pack framings: ``(fill, centre)``, the face box's share of the image (height or width,
#: whichever is smaller) and the height of its centre as a fraction of the image's. ``face``: the
#: face alone, edge to edge; ``head``: the whole head (hair, ears, the top of the neck) with a margin
#: that a moving head stays inside; ``bust``: head and shoulders.
FRAMINGS = {"face": (0.9, 0.5), "head": (0.6, 0.47), "bust": (0.42, 0.4)}


def canvas_similarity(
    neutral: np.ndarray,
    geometries: np.ndarray,
    layout: Layout,
    size: tuple[int, int],
    *,
    framing: str = "face",
    footage: tuple[int, int] | None = None,
) -> np.ndarray:
    """The similarity that puts the neutral face upright and the clip's faces in an image of ``size``.

    The neutral's eye line (outer eye corners, :data:`stages.geometry.signals.EYE_OUTER`) is made
    horizontal; the box spanned by the ``geometries`` (from the 1st percentile of the frames'
    smallest coordinates to the 99th of their largest: a rare landmark glitch does not shrink
    the face) is scaled to the ``framing``'s fill of the image height or width, whichever is
    smaller, centred across and placed at the framing's height (:data:`FRAMINGS`).

    Given the ``footage`` size ``(W, H)``, the image stays inside the footage where it can: it is
    moved (the face box kept inside the image) and, where the footage is too small for the
    framing, the face is enlarged towards the ``face`` framing's fill, the least that fits. Where
    even that does not fit, the framing's own placement is kept (the pack's mattes mark what
    lies beyond the footage).

    Parameters
    ----------
    neutral : (N, 2) float, px
    geometries : (K, N, 2) float, px
        The usable frames' points, already aligned to the neutral's frame.
    size : (W, H) px
    framing : ``"face" | "head" | "bust"``
    footage : (W, H) px, optional
        The frames' size, in the same pixels as ``neutral``.

    Returns
    -------
    (4,) float64 ``(a, b, tx, ty)``, neutral frame -> pack image.
    """
    W, H = size
    left, right = (neutral[layout.index(n)] for n in EYE_OUTER)
    direction = complex(*(right - left))
    if abs(direction) == 0:
        raise ValueError("the neutral's outer eye corners coincide")
    rot = np.conj(direction) / abs(direction)
    z = (geometries[..., 0] + 1j * geometries[..., 1]) * rot
    x0, y0 = np.percentile(z.real.min(axis=-1), 1), np.percentile(z.imag.min(axis=-1), 1)
    x1, y1 = np.percentile(z.real.max(axis=-1), 99), np.percentile(z.imag.max(axis=-1), 99)
    fill, centre = FRAMINGS[framing]

    def placed(f: float) -> tuple[np.ndarray, np.ndarray]:
        """The similarity at fill ``f`` and the face box ``(2, 2)`` it puts in the image."""
        scale = f * min(H / (y1 - y0), W / (x1 - x0))
        t = complex((W - 1) / 2, centre * (H - 1)) - complex((x0 + x1) / 2, (y0 + y1) / 2) * scale
        c = rot * scale
        return np.array([c.real, c.imag, t.real, t.imag]), np.array([[x0, y0], [x1, y1]]) * scale + [t.real, t.imag]

    if footage is not None:
        for f in np.linspace(fill, max(fill, FRAMINGS["face"][0]), 13):
            params, box = placed(f)
            inside = inside_footage(params, size, footage, box)
            if inside is not None:
                return inside
    return placed(fill)[0]


def inside_footage(
    params: np.ndarray, size: tuple[int, int], footage: tuple[int, int], face_box: np.ndarray
) -> np.ndarray | None:
    """``params`` (footage -> image similarity) moved so that the image of ``size`` lies inside the
    footage of size ``footage``, the ``face_box`` ``(2, 2)`` (its corners in the image, px) staying
    inside the image; None when no move does both (the image's axes-aligned extent in the footage
    is what must fit)."""
    W, H = size
    c = complex(params[0], params[1])
    t = complex(params[2], params[3])
    corners = np.array([0, W - 1, (W - 1) + 1j * (H - 1), 1j * (H - 1)])
    back = (corners - t) / c  # the image's corners in the footage
    lo = np.array([back.real.min(), back.imag.min()])
    hi = np.array([back.real.max(), back.imag.max()])
    span = np.array(footage, np.float64)
    if np.any(hi - lo > span - 1):
        return None
    shift = np.clip(lo, 0, None) - lo + np.clip(span - 1 - hi, None, 0)  # footage px, moving the window
    t_new = t - c * complex(*shift)
    moved = np.asarray(face_box, np.float64) + [(t_new - t).real, (t_new - t).imag]
    if moved.min() < 0 or moved[:, 0].max() > W - 1 or moved[:, 1].max() > H - 1:
        return None
    return np.array([c.real, c.imag, t_new.real, t_new.imag])


def k_center(
    features: np.ndarray, k: int, *, seeds: list[int] | tuple[int, ...], min_distance: float = 0.0
) -> tuple[list[int], list[float]]:
    """Greedy k-center (Gonzalez 1985): add the point farthest from the chosen ones.

    Parameters
    ----------
    features : (T, D) float
        One row per candidate; distances are Euclidean.
    k : int
        How many to choose in all, seeds included.
    seeds : sequence of int
        Rows chosen first, in order (at least one).
    min_distance : float
        Stop early when the farthest candidate is no farther than this from the chosen ones
        (no more distinct candidates).

    Returns
    -------
    chosen : list of int
        Rows in the order chosen (``min(k, ...)`` long, seeds first).
    radii : list of float
        ``radii[j]``: the coverage radius after the first ``j + 1`` rows were chosen,
        ``max_i min_{c <= j} ||f_i - f_c||``; non-increasing.
    """
    features = np.asarray(features, np.float64)
    if features.ndim != 2 or len(features) == 0:
        raise ValueError(f"expected features (T, D) with T >= 1, got {features.shape}")
    if not seeds:
        raise ValueError("k_center needs at least one seed row")
    if k < 1:
        raise ValueError(f"expected k >= 1, got {k}")
    chosen: list[int] = []
    radii: list[float] = []
    nearest = np.full(len(features), np.inf)
    for row in seeds:
        if len(chosen) == k:
            break
        chosen.append(int(row))
        nearest = np.minimum(nearest, np.linalg.norm(features - features[row], axis=1))
        radii.append(float(nearest.max()))
    while len(chosen) < k:
        far = int(np.argmax(nearest))
        if nearest[far] <= min_distance:
            break
        chosen.append(far)
        nearest = np.minimum(nearest, np.linalg.norm(features - features[far], axis=1))
        radii.append(float(nearest.max()))
    return chosen, radii


@dataclass
class Selection:
    """The frames chosen for a pack (indices into the clip) and how they map into the pack's image.

    ``to_pack (T, 4)``: per frame the similarity frame -> pack image; ``example_radius_px`` /
    ``captured_radius_px``: coverage radii of the examples / captured set over the candidate frames
    (RMS point distance, pack px); ``warnings``: what the selection could not do as asked.
    """

    neutral: int
    standard: int
    examples: list[int]
    teeth: list[int]
    captured: list[int]
    to_pack: np.ndarray
    example_radius_px: float
    captured_radius_px: float
    mouth_open: np.ndarray
    warnings: list[str] = field(default_factory=list)
    states: dict[str, int] = field(default_factory=dict)  # state -> the frame that seeded it


def select_frames(
    xy: np.ndarray,
    keep: np.ndarray,
    *,
    layout: Layout,
    blendshapes: np.ndarray,
    blendshape_names: np.ndarray,
    matrix: np.ndarray,
    angles: np.ndarray,
    teeth_fraction: np.ndarray,
    size: tuple[int, int],
    n_examples: int = 12,
    n_captured: int = 35,
    n_teeth: int = 4,
    min_distinct_px: float = 1.0,
    pose_deg: float = 10.0,
    min_teeth_open: float = 0.08,
    min_teeth_fraction: float = 0.1,
    depth: np.ndarray | None = None,
    framing: str = "face",
    footage: tuple[int, int] | None = None,
) -> Selection:
    """Choose the pack's frames among the usable ones.

    - **neutral**: the least expressive usable frame with both eyes open (and the lips sealed when
      any usable frame seals them) (:func:`stages.geometry.rigid3d.choose_reference`: blendshape
      activity, head angle, lip gap);
    - **candidates** for everything else: the usable frames whose yaw and pitch are within
      ``pose_deg`` of the neutral's (roll is in the image plane: the similarity removes it). A 2D
      similarity cannot undo a turn or a nod, and the geometry of a nodding head would otherwise
      count as a distinct expression; all usable frames, with a warning, if fewer than 2 are;
    - **examples**: :func:`k_center` over the aligned candidate geometries from the neutral and the
      most extreme frame of each state the candidates show (:data:`STATE_PRIORITY`), ``n_examples``
      in all, stopping early when no candidate is ``min_distinct_px`` from the chosen ones;
    - **captured**: the same sequence continued to ``n_captured`` (examples included);
    - **standard**: the candidate with the widest mouth opening and both eyes open;
    - **teeth**: candidates with the lips apart (``>= min_teeth_open`` eye distances) and teeth
      visible (``teeth_fraction >= min_teeth_fraction``), ``n_teeth`` different openings by
      :func:`k_center` on the opening from the widest; the widest opening alone if none shows teeth.

    Parameters
    ----------
    xy : (T, N, 2) float
        Layout points per frame, px (frame coordinates).
    keep : (T,) bool
        Usable frames (:func:`stages.packbuild.filters.classify_frames`); at least 2.
    blendshapes : (T, 52), blendshape_names : (52,), matrix : (T, 4, 4)
        The landmarker's outputs.
    angles : (T, 3) float
        Yaw, pitch, roll in degrees.
    teeth_fraction : (T,) float
    size : (W, H)
        The pack's image size, px.
    depth : (T, N) float, optional
        The points' depth from the landmarker, px (``landmarks.layout``'s ``z``): geometries are
        compared with the head rotation removed in 3D (module docstring).
    framing : ``"face" | "head" | "bust"``
        How much of the person the pack's image holds (:data:`FRAMINGS`).
    footage : (W, H), optional
        The frames' size: the pack's image stays inside it where it can (:func:`canvas_similarity`).

    Raises
    ------
    ValueError
        Fewer than 2 usable frames.
    """
    xy = np.asarray(xy, np.float64)
    keep = np.asarray(keep, bool)
    angles = np.asarray(angles, np.float64)
    if keep.sum() < 2:
        raise ValueError(f"{int(keep.sum())} usable frame(s); a pack needs at least 2")
    warnings: list[str] = []
    safe = np.where(keep[:, None, None], xy, xy[np.flatnonzero(keep)[0]])
    mouth_open = expression_signals(safe, layout.point_names)["mouth_open"]
    eyes_open = both_eyes_open(safe, keep, layout.point_names)
    rest = keep & eyes_open if (keep & eyes_open).any() else keep
    if (rest & (mouth_open < SEALED_GAP)).any():
        rest &= mouth_open < SEALED_GAP
    neutral = choose_reference(blendshapes, blendshape_names, matrix, mouth_open, rest, search_frames=len(xy))
    near = keep & (np.abs(angles[:, :2] - angles[neutral, :2]) <= pose_deg).all(axis=1)
    if near.sum() < 2:
        warnings.append(
            f"fewer than 2 usable frames within {pose_deg:g} degrees of the neutral's yaw and pitch; "
            f"all {int(keep.sum())} usable frames are candidates"
        )
        near = keep
    usable = np.flatnonzero(near)
    columns = stable_columns(layout)
    to_neutral = align_to_reference(xy, keep, xy[neutral], columns)
    in_neutral = np.stack([apply_similarity(to_neutral[t], xy[t]) for t in usable])
    canvas = canvas_similarity(xy[neutral], in_neutral, layout, size, framing=framing, footage=footage)
    to_pack = compose_similarity(canvas, to_neutral)
    if depth is not None:
        xyz = np.concatenate(
            [np.where(keep[:, None, None], xy, 0.0), np.nan_to_num(np.asarray(depth, np.float64))[..., None]], -1
        )
        d = compensate_rigid3d(
            xyz, np.broadcast_to(keep[:, None], xy.shape[:2]), neutral, np.array(layout.indices(RIGID_POINTS))
        )["d"]
        in_neutral = xy[neutral] + d[usable]
    features = apply_similarity(canvas, in_neutral).reshape(len(usable), -1)
    features /= np.sqrt(layout.n_points)  # Euclidean distance = RMS point distance, px
    seed = int(np.searchsorted(usable, neutral))
    states = state_seeds(safe, usable, neutral, layout.point_names, limit=n_examples - 1)
    seeds = [seed] + [int(np.searchsorted(usable, t)) for t in dict.fromkeys(states.values()) if t != neutral]
    order, radii = k_center(features, n_captured, seeds=seeds, min_distance=min_distinct_px)
    examples = order[:n_examples]
    if len(examples) < n_examples:
        warnings.append(
            f"only {len(examples)} distinct expressions (>= {min_distinct_px:g} px apart) among "
            f"{usable.size} candidate frames; {n_examples} examples were asked"
        )
    if len(examples) < 2:
        examples = [seed, int(np.argmax(np.linalg.norm(features - features[seed], axis=1)))]
        order = examples
        radii = [radii[0], 0.0]
    if len(order) < n_captured:
        warnings.append(f"{len(order)} captured geometries instead of {n_captured}: no more distinct expressions")
    open_eyed = usable[eyes_open[usable]] if eyes_open[usable].any() else usable
    standard = int(open_eyed[np.argmax(mouth_open[open_eyed])])
    shows_teeth = near & (mouth_open >= min_teeth_open) & (np.asarray(teeth_fraction) >= min_teeth_fraction)
    if shows_teeth.any():
        candidates = np.flatnonzero(shows_teeth)
        widest = int(np.argmax(mouth_open[candidates]))
        picked, _ = k_center(mouth_open[candidates, None], n_teeth, seeds=[widest], min_distance=0.0)
        teeth = [int(candidates[j]) for j in picked]
    else:
        teeth = [standard]
        warnings.append(
            f"no candidate frame shows teeth (lips >= {min_teeth_open:g} eye distances apart and >= "
            f"{min_teeth_fraction:.0%} teeth pixels); the widest opening is the only teeth example"
        )
    return Selection(
        neutral=int(neutral),
        standard=standard,
        examples=[int(usable[j]) for j in examples],
        teeth=teeth,
        captured=[int(usable[j]) for j in order],
        to_pack=to_pack,
        example_radius_px=float(radii[len(examples) - 1]),
        captured_radius_px=float(radii[len(order) - 1]),
        mouth_open=mouth_open,
        warnings=warnings,
        states=states,
    )


def both_eyes_open(xy: np.ndarray, keep: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    """``(T,)`` bool: both eyes at least :data:`EYES_OPEN_FRACTION` of their open level (the 90th
    percentile of each eye's lid gap over the ``keep`` frames)."""
    signals = state_signals(xy, names)
    out = np.ones(len(xy), bool)
    for side in "lr":
        gap = signals[f"eye_open_{side}"]
        out &= gap >= EYES_OPEN_FRACTION * np.percentile(gap[keep], 90)
    return out


def state_seeds(xy: np.ndarray, candidates: np.ndarray, neutral: int, names: tuple[str, ...], *, limit: int) -> dict[str, int]:
    """The most extreme candidate frame of each expression state the candidates show (relative to
    the neutral frame), in :data:`STATE_PRIORITY` order; a state that a frame already chosen shows
    takes that frame; at most ``limit`` distinct frames; both eyes shut at once (a blink) is
    preferred for either eye's shut state. Returns ``{state: frame}`` for the states shown."""
    values = state_values(xy[candidates], names, xy[neutral])
    by_name = {s.name: s for s in STATES}
    present = {name: by_name[name].present(values[name]) for name in STATE_PRIORITY}
    blink = present["eye_l_shut"] & present["eye_r_shut"]
    chosen: dict[str, int] = {}
    picked: list[int] = []  # positions in ``candidates``
    for name in STATE_PRIORITY:
        if not present[name].any():
            continue
        shown = [k for k in picked if present[name][k]]
        if shown:
            chosen[name] = int(candidates[shown[0]])
            continue
        if len(picked) >= limit:
            continue
        score = values[name] if by_name[name].below is not None else -values[name]
        if name.endswith("_shut") and blink.any():
            score = np.where(blink, np.maximum(values["eye_l_shut"], values["eye_r_shut"]), np.inf)
        picked.append(int(np.nanargmin(score)))
        chosen[name] = int(candidates[picked[-1]])
    return chosen
