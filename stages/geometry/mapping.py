"""Expression mapping's geometric step (paper Sec. 11, 14.1): the performer's motion-compensated
displacement vectors carried onto the target's neutral geometry.

Traditional expression mapping adds the performer's displacement ``d_i = T^-1(x'_i) - x_i``
(Sec. 12) to the target's neutral point ``y_i``. Faces differ in size and the two neutrals in
in-plane orientation, so the displacements are first brought into the target's frame by the
linear part ``S`` of a normalization: the target geometry is ``y_i + S_i d_i``.

``mode``:

- ``eyes_nose`` (default): ``S = [[a, -b], [b, a]]`` of the least-squares similarity (eq. 8-9)
  mapping the performer's neutral :data:`NORMALIZATION_POINTS` onto the target's: the inner and
  outer eye corners and the nose tip and base (endocanthion, exocanthion, pronasale, subnasale).
  These are anatomical landmarks that a landmark mesh on a real face and the annotation of an
  actor pack place alike; the nose points add the vertical extent (eye line to nose base) that the
  eye corners alone lack. The face-size ratio and the in-plane rotation between the two neutrals.
- ``similarity``: the same similarity fitted on the layout's rigid points (the paper's hairline
  points and inner eye corners, Sec. 12.1). On a real face the hairline is a stand-in (a landmark
  mesh has none; it is extrapolated and may sit lower than the target's), which inflates the
  mapped motion on real clips (x1.25-1.42).
- ``region``: the rotation of ``similarity`` with a scale per feature point set of the layout's
  hierarchy level 1 (Sec. 10): the RMS radius about their centroid of the set's points on the
  target's neutral over the same on the performer's. A point in several sets takes the mean of
  their scales; a point in none, or a set with fewer than 3 tracked points, the global scale.
- ``none``: ``S = I``, displacements in px as they are.

Then the states and guards (:class:`ExpressionMap`):

- ``lids: ratio`` (default): each eye closes by the performer's fraction of its own open gap
  (:func:`lid_ratio`): shut is shut and a wink a wink on any pair of faces, whatever their eye
  shapes; ``displacement`` scales the lids like every point.
- ``close_lips`` (default): the target's neutral is taken with its inner lips closed, as the
  performer's (``compensate.rigid3d``), so a performer's sealed lips seal the target's even when
  the pack's neutral has them apart.
- ``range``: displacements beyond the range the target pack's captured geometries span about its
  neutral (Sec. 10, 14) are ``none`` (default: kept as they are, the warp makes the geometry
  the pack never showed), ``limit`` (each component passed through :func:`soft_limit`,
  saturating smoothly ``range_margin`` beyond the range) or ``relative`` (the performer's own
  range scaled onto the pack's, :func:`relative_range`).
- the inner lips, and the lids, never cross (:func:`separate_lips`): where a mapped upper point
  comes below the lower one facing it (:data:`INNER_LIP_PAIRS`, :data:`LID_PAIRS`), both move
  apart by half the overlap each, to touching (or to the target neutral's own slight overlap).
- the states the mapped geometry demands beyond what the pack's example expressions show
  (:mod:`stages.geometry.states`) are flagged per frame and named in one warning line.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from runner.stage import Context, Param, SequenceStage, StageError
from stages.geometry.bundles import DISPLACEMENTS, POINTS
from stages.pack.bundle_types import LAYOUT, PACK_GEOMETRY
from stages.geometry.rigid3d import close_reference_lips
from stages.geometry.signals import eye_line_frame
from stages.geometry.similarity import fit_similarity
from stages.geometry.states import STATE_NAMES, beyond_coverage, coverage, lid_columns, state_values
from stages.geometry.subset import named_columns, rigid_columns
from stages.pack.bundles import layout_and_geometry

MODES = ("eyes_nose", "similarity", "region", "none")
RANGES = ("limit", "relative", "none")
LIDS = ("ratio", "displacement")
NORMALIZATION_POINTS = ("eye_l_0", "eye_l_6", "eye_r_0", "eye_r_6", "nose_tip", "nose_base")
EYE_CORNERS = (("eye_l_0", "eye_l_6"), ("eye_r_0", "eye_r_6"))  # (inner, outer) of each eye
# (upper, lower) inner-lip points facing each other: the layout's inner lip line runs 1-4 left to
# right on the upper lip and 6-9 right to left on the lower one; 2 and 7 are the middles of the
# two lips that the tracked subset carries.
INNER_LIP_PAIRS = (
    ("mouth_inner_1", "mouth_inner_9"),
    ("mouth_inner_2", "mouth_inner_8"),
    ("mouth_inner_3", "mouth_inner_7"),
    ("mouth_inner_4", "mouth_inner_6"),
    ("mouth_inner_2", "mouth_inner_7"),
)


def rms_radius(xy: np.ndarray) -> float:
    """RMS distance ``(n, 2) -> float`` of points from their centroid, px."""
    return float(np.sqrt(np.mean(np.sum((xy - xy.mean(axis=0)) ** 2, axis=1))))


def reference_columns(names: np.ndarray, layout: Any, mode: str, *, stage: str) -> np.ndarray:
    """Columns ``(R,)`` among the bundle's point ``names`` that the global similarity of ``mode``
    is fitted on: the :data:`NORMALIZATION_POINTS` for ``eyes_nose``, the layout's rigid points
    otherwise; a :class:`StageError` naming ``stage`` when fewer than 2 are there."""
    if mode != "eyes_nose":
        return rigid_columns(names, layout, at_least=2, stage=stage)
    columns = named_columns(names, NORMALIZATION_POINTS)
    if len(columns) < 2:
        raise StageError(
            f"{stage}: mode eyes_nose needs at least 2 of the points {list(NORMALIZATION_POINTS)}; "
            f"the displacements carry {len(columns)}"
        )
    return columns


def displacement_transforms(
    performer: np.ndarray,
    target: np.ndarray,
    reference: np.ndarray,
    *,
    mode: str = "eyes_nose",
    regions: Sequence[np.ndarray] = (),
) -> np.ndarray:
    """The linear maps ``S_i (N, 2, 2)`` applied to each point's displacement.

    Parameters
    ----------
    performer, target : (N, 2) float
        The performer's and the target's neutral geometry of the same N points, px.
    reference : (R,) int
        Columns of the points the global similarity is fitted on (:func:`reference_columns`:
        the normalization points for ``eyes_nose``, the rigid points for ``similarity`` and
        ``region``).
    mode : str
        ``eyes_nose``, ``similarity``, ``region`` or ``none`` (module docstring).
    regions : sequence of (K,) int arrays
        Columns of each region (``region`` mode).
    """
    n = len(performer)
    if mode == "none":
        return np.broadcast_to(np.eye(2), (n, 2, 2)).copy()
    if mode not in MODES:
        raise ValueError(f"unknown mapping mode {mode!r}; expected one of {MODES}")
    a, b, _, _ = fit_similarity(performer[reference], target[reference])
    scale = np.hypot(a, b)
    rotation = np.array([[a, -b], [b, a]]) / scale
    scales = np.full(n, scale)
    if mode == "region":
        total, count = np.zeros(n), np.zeros(n)
        for columns in regions:
            if len(columns) >= 3:
                total[columns] += rms_radius(target[columns]) / rms_radius(performer[columns])
                count[columns] += 1
        scales = np.where(count > 0, total / np.maximum(count, 1), scale)
    return scales[:, None, None] * rotation[None]


def map_expression(d: np.ndarray, target: np.ndarray, transforms: np.ndarray) -> np.ndarray:
    """Target geometry ``y_i + S_i d_i``: ``d (T, N, 2)``, ``target (N, 2)``, ``transforms
    (N, 2, 2)`` -> ``(T, N, 2)`` px."""
    return target[None] + np.einsum("nij,tnj->tni", transforms, d)


def eye_distance(xy: np.ndarray, names: Sequence[str]) -> float:
    """Distance ``(N, 2) -> float`` px between the two eye centres, each the midpoint of the eye's
    inner and outer corner (:data:`EYE_CORNERS`), found by point name."""
    columns = named_columns(np.asarray(names), tuple(n for eye in EYE_CORNERS for n in eye))
    if len(columns) != 4:
        raise ValueError(
            f"the eye distance needs the points {[n for eye in EYE_CORNERS for n in eye]}; found {len(columns)} of them"
        )
    centres = np.asarray(xy, dtype=np.float64)[columns].reshape(2, 2, 2).mean(axis=1)
    return float(np.linalg.norm(centres[1] - centres[0]))


def captured_range(captured: np.ndarray, neutral: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The range ``lo, hi (N, 2)`` px of each point's displacement over a pack's captured
    geometries ``(K, N, 2)`` from its ``neutral (N, 2)``, widened to hold 0 (the neutral itself)."""
    d = np.asarray(captured, dtype=np.float64) - np.asarray(neutral, dtype=np.float64)[None]
    return np.minimum(d.min(axis=0), 0.0), np.maximum(d.max(axis=0), 0.0)


def soft_limit(u: np.ndarray, lo: np.ndarray, hi: np.ndarray, *, margin: float) -> np.ndarray:
    """Saturate values smoothly beyond a range, elementwise (shapes broadcast).

    ``u`` on ``[lo, hi]`` is kept; above, ``hi + margin tanh((u - hi) / margin)``, and below,
    ``lo - margin tanh((lo - u) / margin)``: continuous with slope 1 at the range's ends and never
    more than ``margin`` beyond them. ``margin`` 0 clips to ``[lo, hi]``.
    """
    if not margin >= 0:
        raise ValueError(f"margin must be >= 0, got {margin}")
    u = np.asarray(u, dtype=np.float64)
    if margin == 0:
        return np.clip(u, lo, hi)
    with np.errstate(invalid="ignore"):
        above = hi + margin * np.tanh((u - hi) / margin)
        below = lo - margin * np.tanh((lo - u) / margin)
        return np.where(u > hi, above, np.where(u < lo, below, u))


def limit_displacements(
    displacement: np.ndarray, valid: np.ndarray, lo: np.ndarray, hi: np.ndarray, *, margin: float
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`soft_limit` of mapped displacements against each point's captured range.

    Parameters
    ----------
    displacement : (T, n, 2) float
        Mapped displacements ``S_i d_i`` in the target's frame, px.
    valid : (T, n) bool
        Which of them count as limited.
    lo, hi : (n, 2) float
        Each point's range (:func:`captured_range`), px.
    margin : float
        Width of the soft zone beyond the range, px.

    Returns
    -------
    limited : (T, n, 2) float64
        The displacements after the soft limit.
    outside : (T, n) bool
        Valid displacements more than ``margin`` beyond their range in a component (the
        limit took away over a quarter of what lay beyond it).
    """
    outside = ((displacement > hi + margin) | (displacement < lo - margin)).any(axis=2) & valid
    return soft_limit(displacement, lo, hi, margin=margin), outside


def separate_lips(
    xy: np.ndarray, valid: np.ndarray, neutral: np.ndarray, pairs: Sequence[tuple[int, int]]
) -> tuple[np.ndarray, np.ndarray]:
    """Keep upper inner-lip points above the lower ones facing them.

    For each ``(upper, lower)`` column pair in order, the vertical gap ``y_lower - y_upper`` (px,
    y down) is kept at or above ``min(0, gap on the neutral)``: 0, or the neutral's own slight
    overlap of two touching lips, so that the neutral maps to itself. Where a frame's gap is
    smaller, the upper point moves up and the lower one down by half the shortfall each. A move
    only ever widens a gap, so a pair that was kept apart stays apart after the later ones.

    Parameters
    ----------
    xy : (T, N, 2) float
        Mapped geometry, px.
    valid : (T, N) bool
        A pair is guarded in the frames where both of its points are valid.
    neutral : (N, 2) float
        The geometry the mapping starts from (the target's neutral), px.
    pairs : sequence of (upper, lower) int
        Columns of facing points.

    Returns
    -------
    xy : (T, N, 2) float64
        The geometry with the pairs kept apart (a copy).
    clamped : (T,) bool
        Frames where some pair was moved.
    """
    xy = np.array(xy, dtype=np.float64)
    clamped = np.zeros(len(xy), bool)
    for upper, lower in pairs:
        floor = min(0.0, float(neutral[lower, 1] - neutral[upper, 1]))
        shortfall = floor - (xy[:, lower, 1] - xy[:, upper, 1])
        move = valid[:, upper] & valid[:, lower] & (shortfall > 0)
        xy[move, upper, 1] -= 0.5 * shortfall[move]
        xy[move, lower, 1] += 0.5 * shortfall[move]
        clamped |= move
    return xy, clamped


def relative_range(displacement: np.ndarray, valid: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The performer's own range of each point's mapped displacement scaled onto the pack's.

    Per point and component, the displacements on each side of 0 are scaled by
    ``min(1, hi / top)`` (above) and ``min(1, lo / bottom)`` (below), with ``top`` / ``bottom``
    the largest / smallest valid displacement of the clip: a performance that reaches beyond the
    pack is compressed linearly (its peaks keep their shape and timing), one within it is left as
    it is.

    Parameters
    ----------
    displacement : (T, n, 2) float
        Mapped displacements, px.
    valid : (T, n) bool
    lo, hi : (n, 2) float
        The pack's range per point (:func:`captured_range`), px; ``lo <= 0 <= hi``.

    Returns
    -------
    scaled : (T, n, 2) float64
    outside : (T, n) bool
        Valid displacements that were scaled down.
    """
    d = np.asarray(displacement, np.float64)
    masked = np.where(valid[..., None], d, 0.0)
    top, bottom = masked.max(axis=0), masked.min(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        up = np.where(top > hi, hi / top, 1.0)
        down = np.where(bottom < lo, lo / bottom, 1.0)
    scaled = np.where(d > 0, d * up[None], d * down[None])
    outside = ((d > hi[None]) | (d < lo[None])).any(axis=2) & valid
    return scaled, outside


def lid_gaps(xy: np.ndarray, names: Sequence[str]) -> np.ndarray:
    """Each eye's lid gap ``(2,)`` px (image-left, image-right eye) of one geometry ``(N, 2)``:
    the mean over the facing lid pairs of :data:`stages.geometry.states.EYE_PAIRS` along the
    face's down direction."""
    _, _, down, _ = eye_line_frame(np.asarray(xy, np.float64)[None], names)
    gaps = []
    for side in "lr":
        upper, lower = lid_columns(names, side)
        gaps.append(float(np.mean((xy[lower] - xy[upper]) @ down[0])))
    return np.array(gaps)


def lid_ratio(
    displacement: np.ndarray,
    names: Sequence[str],
    performer: np.ndarray,
    target: np.ndarray,
    transforms: np.ndarray,
    *,
    performer_open: np.ndarray | None = None,
) -> np.ndarray:
    """Mapped lid displacements rescaled so that each eye closes by the performer's fraction.

    A size-scaled displacement closes the target's eye only when both faces' eyes are open alike
    relative to their size: a target with rounder eyes stays ajar when the performer shuts hers,
    one with narrower eyes has its lids pushed through each other. Here the component along the
    target's down direction of every lid point's mapped displacement (``eye_*_1..5``, ``_7..11``)
    is scaled by ``(G_t / G_p) / s``, with ``G_t``, ``G_p`` the eye's open lid gap on the target
    and on the performer (:func:`lid_gaps` of the neutrals) and ``s`` the scale of that point's
    transform: a lid gap ``g`` of the performer becomes ``G_t g / G_p`` on the target — shut is
    shut, half-shut is half-shut, wide is as wide, on any pair of faces.

    Parameters
    ----------
    displacement : (T, n, 2) float
        Mapped displacements ``S_i d_i`` of the performer's points ``names (n,)``, px.
    performer, target : (n, 2) float
        The two neutrals at those points, px.
    transforms : (n, 2, 2) float
        The ``S_i`` (:func:`displacement_transforms`).
    performer_open : (2,) float, optional
        The performer's open lid gaps (px) when its neutral's are not (an eye never seen open):
        the neutral's own gap ``g_0`` is then a fraction ``g_0 / G_p`` of open, and the target's
        upper lids come down to that fraction of its gap before the displacements are added.

    Returns
    -------
    (T, n, 2) float64
    """
    d = np.array(displacement, np.float64)
    names = [str(n) for n in names]
    g_rest = lid_gaps(performer, names)
    g_p = g_rest if performer_open is None else np.asarray(performer_open, np.float64)
    g_t = lid_gaps(target, names)
    _, _, down, _ = eye_line_frame(np.asarray(target, np.float64)[None], names)
    n = down[0]
    for k, side in enumerate("lr"):
        if g_p[k] <= 0 or g_t[k] <= 0:
            continue
        columns = named_columns(np.array(names), tuple(f"eye_{side}_{i}" for i in (1, 2, 3, 4, 5, 7, 8, 9, 10, 11)))
        scale = np.sqrt(np.abs(np.linalg.det(transforms[columns])))
        factor = (g_t[k] / g_p[k]) / scale
        normal = d[:, columns] @ n
        d[:, columns] += ((factor - 1.0)[None, :] * normal)[..., None] * n
        closed = 1.0 - min(max(g_rest[k], 0.0) / g_p[k], 1.0)
        if closed > 0:  # the neutral's eye is shut by this fraction: so is the target's at rest
            for u, lw in ((1, 11), (2, 10), (3, 9), (4, 8), (5, 7)):
                upper, lower = (names.index(f"eye_{side}_{i}") for i in (u, lw))
                d[:, upper] += closed * float((target[lower] - target[upper]) @ n) * n
    return d


#: Facing lid points (upper, lower) of each eye, kept apart like the lips.
LID_PAIRS = tuple(
    (f"eye_{side}_{u}", f"eye_{side}_{lw}") for side in "lr" for u, lw in ((1, 11), (2, 10), (3, 9), (4, 8), (5, 7))
)
#: A typical open lid gap, eye distances (the open level of the dev clips' performers is 0.08-0.14):
#: the reference for an eye that is never seen open.
TYPICAL_EYE_OPEN = 0.11


class ExpressionMap(SequenceStage):
    """``map.expression``: performer displacements -> target geometry of the tracked subset.

    The output covers the whole layout of the target's pack, as motion propagation (Sec. 10)
    expects: ``xy (T, N, 2)`` with the mapped tracked points valid and every other point at the
    target's neutral position, flagged invalid (propagation infers it). Besides the ``points``
    keys it carries ``range_limited (T,) bool`` (frames where a valid displacement lay outside the
    pack's captured range, more than the margin for ``range=limit``; what was limited or scaled),
    ``lips_clamped (T,) bool`` (frames where :func:`separate_lips` moved the inner lips or lids
    apart), and the states the pack cannot show (:mod:`stages.geometry.states`):
    ``state_names (S,)``, ``beyond_pack (T, S) bool``, ``coverage (S, 2)`` (the pack's range of
    each state's relative value over its example expressions) and ``state_values (T, S)`` (the
    mapped geometry's).
    """

    name = "map.expression"
    version = "5"
    doc = (
        "performer displacements onto the target's neutral (Sec. 11): size-normalized, eyes closing by the "
        "performer's fraction, range mode, lips and lids never crossing; states beyond the pack listed"
    )
    inputs = {"displacements": DISPLACEMENTS, "layout": LAYOUT, "geometry": PACK_GEOMETRY}
    outputs = {"points": POINTS}
    params = (
        Param("mode", str, "eyes_nose", "displacement normalization (eyes_nose | similarity | region | none)", choices=MODES),
        Param(
            "range",
            str,
            "none",
            "displacements beyond the pack's captured range: limit (saturate softly past the "
            "range + margin), relative (the performer's own range scaled onto the pack's), none (as they are)",
            choices=RANGES,
        ),
        Param(
            "range_margin",
            float,
            0.05,
            "range=limit: how far beyond the captured range a displacement may go, fraction of the target's eye distance",
            min=0.0,
            max=1.0,
        ),
        Param(
            "lids",
            str,
            "ratio",
            "eyelids: ratio (each eye closes by the performer's fraction of its own open "
            "gap) or displacement (size-scaled like every point)",
            choices=LIDS,
        ),
        Param(
            "close_lips",
            bool,
            True,
            "the target's neutral taken with its inner lips closed, as the performer's "
            "(a pack whose neutral has the lips apart otherwise never seals them)",
        ),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        params = {p.name: p.default for p in self.params} | dict(params)
        bundle = inputs["displacements"]
        if "neutral" not in bundle:
            raise StageError(f"{self.name}: the displacements carry no 'neutral' (the performer's neutral geometry)")
        margin = float(params["range_margin"])
        try:
            layout, geometry = layout_and_geometry(inputs["layout"], inputs["geometry"])
        except ValueError as exc:
            raise StageError(f"{self.name}: {exc}") from None
        names = np.asarray(bundle["names"])
        try:
            rows = [layout.index(str(n)) for n in names]
        except (KeyError, ValueError) as exc:
            raise StageError(f"{self.name}: point {exc} is not in the pack's layout {layout.name}") from None
        reference = reference_columns(names, layout, params["mode"], stage=self.name)
        regions = [
            named_columns(names, tuple(layout.point_names[i] for i in fps.points))
            for fps in layout.feature_point_sets
            if fps.level == 1
        ]
        neutral_all = geometry.neutral
        if params["close_lips"]:
            try:
                neutral_all = close_reference_lips(neutral_all, np.zeros((0,) + neutral_all.shape), layout.point_names)[0]
            except KeyError as exc:
                raise StageError(f"{self.name}: close_lips needs the layout point {exc}; set close_lips=false") from None
        target = neutral_all[rows]
        performer = np.asarray(bundle["neutral"], dtype=np.float64)
        transforms = displacement_transforms(performer, target, reference, mode=params["mode"], regions=regions)
        valid_in = np.asarray(bundle["valid"], bool)
        displacement = map_expression(np.asarray(bundle["d"], dtype=np.float64), target, transforms) - target[None]
        if params["lids"] == "ratio":
            displacement = self._lid_ratio(displacement, names, performer, target, transforms, bundle, ctx)
        n_frames = len(displacement)
        outside = np.zeros(valid_in.shape, bool)  # (T, n): beyond the captured range
        if params["range"] != "none":
            lo, hi = captured_range(geometry.captured, geometry.neutral)
            if params["range"] == "limit":
                displacement, outside = limit_displacements(
                    displacement, valid_in, lo[rows], hi[rows], margin=margin * eye_distance(neutral_all, layout.point_names)
                )
            else:
                displacement, outside = relative_range(displacement, valid_in, lo[rows], hi[rows])
        limited = outside.any(axis=1)
        xy = np.repeat(neutral_all[None], n_frames, axis=0)
        xy[:, rows] = target[None] + displacement
        valid = np.zeros((n_frames, layout.n_points), bool)
        valid[:, rows] = valid_in
        pairs = [
            (layout.index(u), layout.index(lw))
            for u, lw in INNER_LIP_PAIRS + LID_PAIRS
            if u in layout.point_names and lw in layout.point_names
        ]
        xy, clamped = separate_lips(xy, valid, neutral_all, pairs)
        per_point = outside.sum(axis=0)
        most = ", ".join(f"{names[i]} {per_point[i]}" for i in np.argsort(-per_point, kind="stable")[:3] if per_point[i])
        ctx.log.info(
            f"{self.name}: displacements beyond the pack's captured range in {int(limited.sum())} of "
            f"{n_frames} frames (range={params['range']})"
            + (f", most often (frames): {most}" if most else "")
            + f"; lips or lids kept apart in {int(clamped.sum())} frames"
        )
        out = {"xy": xy, "valid": valid, "names": np.array(layout.point_names), "range_limited": limited, "lips_clamped": clamped}
        out.update(self._states_beyond_pack(xy, valid, neutral_all, geometry, layout, ctx))
        out.update({k: np.asarray(bundle[k]) for k in ("fps", "size") if k in bundle})
        return {"points": out}

    def _lid_ratio(
        self,
        displacement: np.ndarray,
        names: np.ndarray,
        performer: np.ndarray,
        target: np.ndarray,
        transforms: np.ndarray,
        bundle: Mapping[str, np.ndarray],
        ctx: Context,
    ) -> np.ndarray:
        """:func:`lid_ratio`, with a typical open gap for an eye the displacements say was never open."""
        try:
            lid_columns(names, "l"), lid_columns(names, "r")
        except ValueError:
            return displacement  # a subset without the lids (the paper's tracked points): size-scaled as the rest
        known = np.asarray(bundle.get("eye_open_known", np.ones(2, bool)), bool)
        open_gaps = lid_gaps(performer, names)
        if not known.all():
            typical = TYPICAL_EYE_OPEN * eye_distance(performer, names)
            open_gaps = np.where(known, open_gaps, typical)
        return lid_ratio(displacement, names, performer, target, transforms, performer_open=open_gaps)

    def _states_beyond_pack(
        self, xy: np.ndarray, valid: np.ndarray, neutral: np.ndarray, geometry: Any, layout: Any, ctx: Context
    ) -> dict[str, np.ndarray]:
        """The states the mapped geometry demands beyond the pack's example expressions, and one
        warning line naming them with their frame counts."""
        try:
            values = state_values(xy, layout.point_names, neutral)
        except ValueError:
            return {}  # a layout without the state points
        covered = coverage(geometry.examples, layout.point_names, neutral)
        beyond = beyond_coverage(values, covered, valid.any(axis=1))
        counted = [(name, int(flags.sum())) for name, flags in beyond.items() if flags.any()]
        if counted:
            ctx.log.warning(
                "%s: the performance goes beyond what the target pack's examples show (the warp still "
                "makes the geometry; the texture is the nearest example's): %s",
                self.name,
                ", ".join(f"{name.replace('_', ' ')} {n} frames" for name, n in counted),
            )
        return {
            "state_names": np.array(STATE_NAMES),
            "beyond_pack": np.stack([beyond[n] for n in STATE_NAMES], axis=1),
            "coverage": np.array([covered[n] for n in STATE_NAMES]),
            "state_values": np.stack([values[n] for n in STATE_NAMES], axis=1),
        }
