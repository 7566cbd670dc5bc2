"""Head-motion compensation from the landmarker's 3D points, relative to a chosen reference frame.

The paper removes the performer's head motion with a 2D similarity of the rigid points (Sec. 12,
eq. 8-9), which cannot undo out-of-plane rotation, or with PnP on a generic 3D model (Sec. 12.1).
A face landmarker gives every point a depth as well (MediaPipe: ``z`` in the same pixel scale as
``x``, increasing away from the camera), so each frame's rigid points can be aligned in 3D to the
reference frame's directly, under weak perspective, with no generic model and no intrinsics:

    X_i(t) ~ s(t) R(t) X_i(r) + t(t)                    (i over the rigid points)

solved in closed form per frame (Umeyama's least-squares similarity, with Huber reweighting).
Every point of frame ``t`` is then taken back into the reference frame,
``X'_i = R(t)^T (X_i(t) - t(t)) / s(t)``, and its compensated displacement is the image-plane part
of ``X'_i - X_i(r)`` — the 3D counterpart of the paper's ``T^-1(x') - x``.

Two references, neither assumed. The *head frame* (:func:`choose_reference`: the most frontal,
least expressive frame of the clip, from the landmarker's blendshapes and head matrix) is the frame
every frame is aligned to, so pose and the 2D similarity are relative to it. The *neutral* the
displacements are taken from is estimated over the whole clip, region by region
(:mod:`stages.geometry.neutral`): a clip that starts mid-expression, or never shows a neutral
moment, still has one. A user may name a frame instead (``neutral_frame``). The neutral's inner
lips are closed before the displacements are taken (:func:`close_reference_lips`), so a neutral
with the lips slightly apart does not cost the target that much of its mouth opening. Regions an
occluder hides (an ``occlusion`` bundle) are held from the frames around them
(:func:`hold_occluded`) and never enter the neutral.

The head pose reported (``pose``, the head motion carried onto the target) takes its rotation from
the landmarker's facial transformation matrix relative to the head frame,
``R(t) = L(t) L(r)^T`` (:func:`landmarker_head_motion`), by default: MediaPipe solves it under
full perspective against its metric canonical face, where the weak-perspective fit above reads
every turn larger (a head turning about its centre, some 10 cm behind the face, also shifts the
face sideways, and perspective makes the nearer points shift more: the fit takes that parallax
for rotation). Measured by ``bench.py shot`` (``shot_pose_slope_*``). The displacements always
come from the fit, which removes the motion the points show, whatever its cause.

Coordinates: x right, y down (px, origin at the centre of the top-left pixel), z away from the
camera (px): a right-handed camera frame as OpenCV's. Angles: ``R = Ry(yaw) Rx(pitch) Rz(roll)``,
degrees; yaw about the image's vertical axis, pitch about its horizontal axis, roll in the image
plane.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from runner.stage import SUMMARY, Context, Param, SequenceStage, StageError
from stages.geometry.bundles import DISPLACEMENTS, HEAD_POSE_RELATIVE, POINTS, SIMILARITY
from stages.landmarks.bundles import LANDMARKS
from stages.occlusion.bundles import OCCLUSION
from stages.geometry.compensate import compensate as similarity_2d
from stages.geometry.neutral import REST, NeutralEstimate, estimate_neutral
from stages.geometry.rotation import landmarker_rotation, rodrigues_vector, ypr_yxz
from stages.geometry.signals import expression_signals
from stages.geometry.subset import param_columns

#: Points of the zhang134 layout that move with the skull: eye corners, nose bridge, forehead,
#: temples and the contour beside the eyes (the jaw's contour points move with the mouth).
RIGID_POINTS = (
    "eye_l_0",
    "eye_l_6",
    "eye_r_0",
    "eye_r_6",
    "nose_bridge_0",
    "nose_bridge_1",
    "nose_bridge_2",
    "forehead_l",
    "forehead_c",
    "forehead_r",
    "temple_l",
    "temple_r",
    "contour_0",
    "contour_16",
)

#: The facing inner-lip pairs of the zhang134 layout (upper, lower), left to right, with the teeth
#: edges that lie between them (``teeth_upper_k`` / ``teeth_lower_k`` are mixes of pair k's lips:
#: ``stages/layouts/zhang134_mediapipe.yaml``), for :func:`close_reference_lips`.
LIP_PAIRS = tuple((f"mouth_inner_{k + 1}", f"mouth_inner_{9 - k}", f"teeth_upper_{k}", f"teeth_lower_{k}") for k in range(4))

#: Blendshapes that are not facial expression (gaze direction) and the rest score, MediaPipe names.
_NOT_EXPRESSION = ("_neutral", "eyeLook")


def similarity_3d(src: np.ndarray, dst: np.ndarray, weights: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Weighted least-squares similarity ``dst ~ s R src + t`` in 3D (Umeyama 1991).

    Parameters
    ----------
    src, dst : (n, 3) float
        Corresponding points, ``n >= 3`` not collinear.
    weights : (n,) float
        Non-negative weights of the squared residuals.

    Returns
    -------
    s : float
        Scale.
    R : (3, 3) float64
        Rotation (det +1).
    t : (3,) float64
        Translation.
    """
    w = np.asarray(weights, np.float64) / np.sum(weights)
    mu_s, mu_d = w @ src, w @ dst
    a, b = src - mu_s, dst - mu_d
    cov = (b * w[:, None]).T @ a
    u, sv, vt = np.linalg.svd(cov)
    flip = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    R = u @ flip @ vt
    s = float(np.trace(np.diag(sv) @ flip) / (w @ np.sum(a * a, axis=1)))
    return s, R, mu_d - s * R @ mu_s


def compensate_rigid3d(
    xyz: np.ndarray, valid: np.ndarray, reference: int, rigid: np.ndarray, *, huber_px: float = 2.0, iterations: int = 5
) -> dict[str, np.ndarray]:
    """Per-frame 3D similarity of the rigid points to the reference frame, and the compensated
    displacements of every point.

    Parameters
    ----------
    xyz : (T, N, 3) float
        Points per frame: x, y in px and the landmarker's depth z in px (module docstring).
    valid : (T, N) bool
        Point validity.
    reference : int
        The reference (neutral) frame; its rigid points must be valid.
    rigid : (R,) int
        Columns of the rigid points, ``R >= 3``.
    huber_px : float
        Huber threshold of the iteratively reweighted fit, px (rigid points that move, e.g. a
        forehead point lifted by the brows, lose weight).
    iterations : int
        Reweighting passes.

    Returns
    -------
    dict
        ``d (T, N, 2)`` px, compensated displacements from the reference geometry;
        ``R (T, 3, 3)``, ``s (T,)``, ``t (T, 3)`` px: reference -> frame; ``residual_px (T,)`` RMS
        over the rigid points; ``frame_valid (T,)``: at least 3 valid rigid points (others are
        held from the nearest solved frame, d invalid).
    """
    xyz = np.asarray(xyz, np.float64)
    n_frames = len(xyz)
    ref = xyz[reference]
    R = np.repeat(np.eye(3)[None], n_frames, axis=0)
    s, t = np.ones(n_frames), np.zeros((n_frames, 3))
    residual = np.full(n_frames, np.nan)
    solved = np.zeros(n_frames, bool)
    for f in range(n_frames):
        use = rigid[valid[f, rigid] & valid[reference, rigid]]
        if len(use) < 3:
            continue
        weights = np.ones(len(use))
        for _ in range(iterations + 1):
            s[f], R[f], t[f] = similarity_3d(ref[use], xyz[f, use], weights)
            r = np.linalg.norm(s[f] * ref[use] @ R[f].T + t[f] - xyz[f, use], axis=1)
            weights = np.minimum(1.0, huber_px / np.maximum(r, 1e-9))
        residual[f] = float(np.sqrt(np.mean(r**2)))
        solved[f] = True
    if not solved.any():
        raise ValueError("no frame has 3 valid rigid points shared with the reference frame")
    nearest = nearest_valid(solved)
    R, s, t = R[nearest], s[nearest], t[nearest]
    back = np.einsum("tnk,tkj->tnj", xyz - t[:, None], R) / s[:, None, None]
    d = back[..., :2] - ref[None, :, :2]
    return {"d": d, "R": R, "s": s, "t": t, "residual_px": residual, "frame_valid": solved}


def landmarker_head_motion(
    matrix: np.ndarray, reference: int, R: np.ndarray, s: np.ndarray, t: np.ndarray, centre: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The head motion with the landmarker's rotation: ``R'(t) = L(t) L(r)^T`` from the facial
    transformation matrices (:func:`stages.geometry.rotation.landmarker_rotation`), and the
    translation that moves the rigid points' ``centre`` where the fit moves it,
    ``t' = t + s (R - R') c``.

    Parameters
    ----------
    matrix : (T, 4, 4) float
        The landmarker's facial transformation matrix per frame.
    reference : int
        The head frame.
    R, s, t : (T, 3, 3), (T,), (T, 3) px
        The fitted similarity, reference -> frame (:func:`compensate_rigid3d`).
    centre : (3,) float
        The rigid points' centroid in the reference frame, px.

    Returns
    -------
    R_pose : (T, 3, 3) float64
    t_pose : (T, 3) float64, px
    """
    L = landmarker_rotation(matrix)
    R_pose = L @ L[reference].T
    c = np.asarray(centre, np.float64)
    t_pose = np.asarray(t, np.float64) + np.asarray(s, np.float64)[:, None] * np.einsum("tij,j->ti", R - R_pose, c)
    return R_pose, t_pose


def close_reference_lips(neutral: np.ndarray, d: np.ndarray, names: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The reference geometry with its inner lips closed, and the displacements from it.

    The mapping carries displacements from the performer's reference onto the target's neutral,
    whose lips are closed. When the reference frame has the lips apart, a frame where the performer
    closes them has the lower lip moving up from the reference: the target's lips would cross, the
    crossing is clamped (``map.expression``), and the target's mouth opening loses that part of the
    performer's (robustness campaign, ``docs/realface.md``: on variants of a real clip whose chosen
    reference had the lips 3-5 % of the eye distance apart, the amplitude ratio of the target's
    mouth opening to the performer's was 0.76-0.87; 0.94-0.98 with the lips closed here). Here
    each facing pair of inner-lip points
    (:data:`LIP_PAIRS`) that is apart in the reference is moved onto its midline along the face's
    down direction (the normal of the outer-eye-corner line), with the teeth edges between them,
    and the displacements are taken from that closed reference, ``d' = d + (x_ref - x_closed)``:
    the compensated geometry ``x_closed + d'`` is unchanged, and the target opens its mouth by
    what the performer opens from closed lips, whatever the reference frame. Pairs that touch or
    overlap in the reference are left as they are (a reference with closed lips changes nothing).

    Parameters
    ----------
    neutral : (N, 2) float
        The reference frame's points, px.
    d : (T, N, 2) float
        Displacements from ``neutral``, px.
    names : (N,) str
        Layout point names (zhang134: the pairs, teeth edges and outer eye corners by name).

    Returns
    -------
    closed : (N, 2) float64
        The reference with its inner lips closed.
    d_closed : (T, N, 2) float64
        Displacements from ``closed``.
    gap_px : float
        The largest gap closed, px (0 when none was apart).
    """
    neutral = np.asarray(neutral, np.float64)
    columns = {str(n): i for i, n in enumerate(names)}
    left, right = (neutral[columns[n]] for n in ("eye_l_6", "eye_r_6"))
    if not np.linalg.norm(right - left) > 0:  # no eye line (a placeholder geometry): no face to close
        return neutral.copy(), np.asarray(d, np.float64), 0.0
    along = (right - left) / np.linalg.norm(right - left)
    down = np.array([-along[1], along[0]])  # x right, y down: the eye line turned a quarter, pointing down
    closed = neutral.copy()
    widest = 0.0
    for upper, lower, *teeth in LIP_PAIRS:
        u, lw = columns[upper], columns[lower]
        gap = float((neutral[lw] - neutral[u]) @ down)
        if gap <= 0:
            continue
        widest = max(widest, gap)
        middle = (neutral[u] + neutral[lw]) @ down / 2
        for i in [u, lw] + [columns[t] for t in teeth if t in columns]:
            closed[i] += (middle - neutral[i] @ down) * down
    return closed, np.asarray(d, np.float64) + (neutral - closed)[None], widest


def median_placement(xy: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``(N, 2)`` px: each point's median image position over the frames where it is valid
    (``xy (T, N, 2)``, ``valid (T, N)``); a point valid nowhere takes its first frame's."""
    masked = np.where(valid[..., None], np.asarray(xy, np.float64), np.nan)
    with np.errstate(all="ignore"):
        out = np.nanmedian(masked, axis=0) if valid.any() else np.asarray(xy[0], np.float64)
    return np.where(np.isfinite(out), out, np.asarray(xy[0], np.float64))


def nearest_valid(valid: np.ndarray) -> np.ndarray:
    """``(T,)`` bool -> ``(T,)`` int: each frame's nearest valid frame (itself when valid)."""
    good = np.flatnonzero(valid)
    return good[np.abs(np.arange(len(valid))[:, None] - good[None]).argmin(axis=1)]


def expressiveness(blendshapes: np.ndarray, names: np.ndarray) -> np.ndarray:
    """``(T, 52)`` blendshape scores -> ``(T,)``: the sum of the scores of the expression
    blendshapes (all but ``_neutral`` and the gaze directions ``eyeLook*``)."""
    keep = np.array([not str(n).startswith(_NOT_EXPRESSION) for n in names])
    return np.asarray(blendshapes, np.float64)[:, keep].sum(axis=1)


def choose_reference(
    blendshapes: np.ndarray,
    names: np.ndarray,
    matrix: np.ndarray,
    mouth_open: np.ndarray,
    valid: np.ndarray,
    *,
    search_frames: int,
    degrees_weight: float = 0.05,
    mouth_weight: float = 10.0,
) -> int:
    """The reference (neutral) frame: among the first ``search_frames`` valid frames, the one
    minimizing

        expressiveness + degrees_weight * head angle + mouth_weight * max(mouth opening, 0)

    with the head angle the rotation angle (degrees) of the landmarker's facial transformation
    matrix ``(T, 4, 4)`` and the mouth opening the inner-lip gap in eye distances
    (:func:`stages.geometry.signals.expression_signals`). With the defaults 20 degrees of turn,
    one fully active blendshape and a gap of a tenth of the eye distance weigh the same: a
    reference with the lips apart would push the target's lips through each other whenever the
    performer closes more, and blendshapes barely register a small gap.

    Raises
    ------
    ValueError
        No valid frame.
    """
    candidates = np.flatnonzero(valid)[: max(1, search_frames)]
    if candidates.size == 0:
        raise ValueError("no frame with a face to take as the reference")
    angle = head_angle_deg(np.asarray(matrix, np.float64)[candidates, :3, :3])
    cost = (
        expressiveness(np.asarray(blendshapes)[candidates], names)
        + degrees_weight * angle
        + mouth_weight * np.clip(np.asarray(mouth_open, np.float64)[candidates], 0, None)
    )
    return int(candidates[np.nanargmin(cost)])


def head_angle_deg(R: np.ndarray) -> np.ndarray:
    """``(T, 3, 3)`` rotations (scaled rotations allowed) -> ``(T,)`` rotation angles, degrees."""
    R = R / np.cbrt(np.linalg.det(R))[:, None, None]
    cos = np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1, 1)
    return np.degrees(np.arccos(cos))


def hold_occluded(d: np.ndarray, occluded: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """Displacements of occluded points interpolated in time from the frames around them.

    For each run of occluded frames, the displacements ``d (T, N, 2)`` of ``columns`` go linearly
    from the last frame before the run to the first frame after it; a run at the clip's start or
    end holds the one neighbour it has, and a region occluded in every frame stays at the neutral
    (zero displacement). Returns a copy.

    Parameters
    ----------
    d : (T, N, 2) float
        Compensated displacements, px.
    occluded : (T,) bool
        Frames where the region is hidden.
    columns : (K,) int
        The region's points.
    """
    d = np.array(d, np.float64)
    occluded = np.asarray(occluded, bool)
    if not occluded.any() or len(columns) == 0:
        return d
    if occluded.all():
        d[:, columns] = 0.0
        return d
    edges = np.diff(np.concatenate([[0], occluded.astype(np.int8), [0]]))
    for first, end in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)):
        before, after = first - 1, end
        if before < 0:
            d[first:end][:, columns] = d[after, columns]
        elif after >= len(d):
            d[first:end][:, columns] = d[before, columns]
        else:
            w = ((np.arange(first, end) - before) / (after - before))[:, None, None]
            d[first:end][:, columns] = (1 - w) * d[before, columns] + w * d[after, columns]
    return d


def occluded_regions(
    occlusion: Mapping[str, np.ndarray] | None, names: np.ndarray, n_frames: int
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{region: (occluded (T,) bool, columns (K,) int)}`` from an ``occlusion`` bundle
    (``regions (R,)``, ``occluded (T, R)``, ``region_points (R, M)`` over its ``names (M,)``),
    the columns among this bundle's ``names``; empty without one."""
    if occlusion is None:
        return {}
    flags = np.asarray(occlusion["occluded"], bool)
    if flags.shape[0] != n_frames:
        raise ValueError(f"the occlusion bundle has {flags.shape[0]} frames, the points {n_frames}")
    where = {str(n): i for i, n in enumerate(names)}
    theirs = [str(n) for n in occlusion["names"]]
    out = {}
    for r, region in enumerate(occlusion["regions"]):
        members = np.asarray(occlusion["region_points"], bool)[r]
        columns = np.array([where[theirs[m]] for m in np.flatnonzero(members) if theirs[m] in where], np.int64)
        out[str(region)] = (flags[:, r], columns)
    return out


class CompensateRigid3D(SequenceStage):
    """``compensate.rigid3d``: head motion removed by 3D alignment of the landmarker's points to a
    head frame, displacements from the performer's neutral estimated over the whole clip (an
    extension of Sec. 12 for real footage)."""

    name = "compensate.rigid3d"
    version = "7"
    doc = (
        "neutral estimated from the whole clip (or a named frame); 3D similarity of the rigid points; "
        "displacements, pose, 2D similarity; occluded regions held"
    )
    inputs = {"points": POINTS, "landmarks": LANDMARKS, "occlusion": OCCLUSION}
    optional_inputs = frozenset({"occlusion"})
    outputs = {"displacements": DISPLACEMENTS, "similarity": SIMILARITY, "pose": HEAD_POSE_RELATIVE}
    params = (
        Param(
            "neutral_frame",
            int,
            -1,
            "the reference (neutral) frame; -1: the neutral is estimated region by region "
            "from the whole clip, and the head frame chosen as the most frontal, least expressive frame",
            min=-1,
            max=10_000_000,
        ),
        Param(
            "search_frames",
            int,
            0,
            "frames searched for the head frame, from the first with a face (0: the whole clip)",
            min=0,
            max=10_000_000,
        ),
        Param(
            "max_turn_deg",
            float,
            20.0,
            "frames turned more than this from the head frame do not enter the estimated neutral",
            min=1.0,
            max=90.0,
        ),
        Param("rigid_points", list, list(RIGID_POINTS), "layout points aligned in 3D (they move with the skull)", items=str),
        Param("huber_px", float, 2.0, "Huber threshold of the robust 3D fit, px", min=0.01, max=100.0),
        Param(
            "pose_rotation",
            str,
            "landmarker",
            "the head pose's rotation: the landmarker's facial transformation matrix relative to the head "
            "frame (perspective), or the weak-perspective fit of the rigid points",
            choices=("landmarker", "points"),
        ),
        Param("warn_angle_deg", float, 12.0, "warn when the head frame is turned more than this", min=0.0, max=90.0),
        Param(
            "warn_expression",
            float,
            2.0,
            "warn when a named reference frame's expressiveness (sum of blendshapes) exceeds this",
            min=0.0,
            max=100.0,
        ),
        Param(
            "close_lips",
            bool,
            True,
            "displacements from the neutral with its inner lips closed (a neutral with "
            "the lips apart would cost the target that much mouth opening)",
        ),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        params = {p.name: p.default for p in self.params} | dict(params)
        points, marks = inputs["points"], inputs["landmarks"]
        if "z" not in points:
            raise StageError(f"{self.name}: input 'points' carries no depth 'z' (use landmark points)")
        xy = np.asarray(points["xy"], np.float64)
        valid = np.asarray(points["valid"], bool)
        names = np.asarray(points["names"])
        n_frames = len(xy)
        if len(marks["valid"]) != n_frames:
            raise StageError(f"{self.name}: {n_frames} frames of points but {len(marks['valid'])} of landmarks")
        frame_ok = np.asarray(marks["valid"], bool) & valid.any(axis=1)
        named = int(params["neutral_frame"])
        if named >= n_frames or (named >= 0 and not frame_ok[named]):
            raise StageError(
                f"{self.name}: neutral_frame={named}: the clip has {n_frames} frames and that frame must show the face"
            )
        try:
            occlusion = occluded_regions(inputs.get("occlusion"), names, n_frames)
            hidden = np.any([flags for flags, _ in occlusion.values()], axis=0) if occlusion else np.zeros(n_frames, bool)
            reference = named
            if reference < 0:
                mouth = expression_signals(xy, names)["mouth_open"]
                search = int(params["search_frames"]) or n_frames
                reference = choose_reference(
                    marks["blendshapes"],
                    marks["blendshape_names"],
                    marks["matrix"],
                    mouth,
                    frame_ok & ~hidden if (frame_ok & ~hidden).any() else frame_ok,
                    search_frames=search,
                )
            rigid = param_columns(names, params["rigid_points"], stage=self.name, param="rigid_points")
            # Frames without a face hold the nearest frame with one: the target keeps that expression
            # (displacements valid, ``held`` True) while the points and pose stay flagged invalid.
            held = nearest_valid(frame_ok)
            xy, valid = xy[held], valid[held]
            xyz = np.concatenate([xy, np.asarray(points["z"], np.float64)[held][..., None]], axis=-1)
            fit = compensate_rigid3d(xyz, valid, reference, rigid, huber_px=float(params["huber_px"]))
            aligned = xy[reference][None] + fit["d"]
            if named >= 0:
                estimate = None
                neutral = xy[reference].copy()
            else:
                faces = frame_ok & fit["frame_valid"]
                eligible = faces & (head_angle_deg(fit["R"]) <= float(params["max_turn_deg"]))
                if not eligible.any():
                    ctx.log.warning(
                        "%s: every frame is turned more than %g deg from the head frame %d; the neutral "
                        "is estimated from all frames with a face",
                        self.name,
                        params["max_turn_deg"],
                        reference,
                    )
                    eligible = faces
                estimate = estimate_neutral(
                    np.where(valid[..., None], aligned, np.nan),
                    names,
                    eligible,
                    np.asarray(marks["blendshapes"])[held],
                    marks["blendshape_names"],
                    occluded={region: flags for region, (flags, _) in occlusion.items()},
                )
                neutral = estimate.neutral
        except (KeyError, ValueError) as exc:
            raise StageError(f"{self.name}: {exc}") from None
        self._log_reference(ctx, reference, estimate, marks, params, names)
        frame_valid = fit["frame_valid"] & frame_ok
        d_valid = valid & np.isfinite(neutral).all(axis=1)[None] & fit["frame_valid"][:, None]
        if (~frame_ok).any():
            ctx.log.warning(
                "%s: no face in %d of %d frames; each holds the expression of the nearest frame with one",
                self.name,
                int((~frame_ok).sum()),
                n_frames,
            )
        d = aligned - neutral[None]
        if params["close_lips"]:
            try:
                neutral, d, gap = close_reference_lips(neutral, d, names)
            except KeyError as exc:
                raise StageError(f"{self.name}: close_lips needs the layout point {exc}; set close_lips=false") from None
            if gap > 0:
                ctx.log.info(
                    "%s: the neutral's lips are apart (up to %.1f px): displacements are taken from the "
                    "neutral with its lips closed",
                    self.name,
                    gap,
                )
        occluded_any = np.zeros(n_frames, bool)
        for region, (flags, columns) in occlusion.items():
            d = hold_occluded(d, flags, columns)
            occluded_any |= flags
        if occluded_any.any():
            counts = ", ".join(f"{region} {int(flags.sum())}" for region, (flags, _) in occlusion.items() if flags.any())
            ctx.log.warning("%s: occluded regions held from the frames around them (frames: %s)", self.name, counts)
        extra = {k: np.asarray(points[k]) for k in ("fps", "size") if k in points}
        known = (
            np.array([estimate.eye_open_known.get(f"eye_{s}", True) for s in "lr"]) if estimate is not None else np.ones(2, bool)
        )
        displacements = {
            "d": d,
            "valid": d_valid,
            "names": names,
            "neutral": neutral,
            "neutral_frame": np.array(reference),
            "neutral_estimated": np.array(estimate is not None),
            "neutral_nearest_frame": np.array(reference if estimate is None else estimate.nearest_frame),
            "eye_open_known": known,
            "held": ~frame_ok,
            "occluded": occluded_any,
            **extra,
        }
        # The head motion carried onto the output: relative to the named frame, or to the clip's median
        # head placement (per point over the frames with a face), so that no one frame decides where
        # the target sits.
        rest = xy[reference] if estimate is None else median_placement(xy, valid & frame_ok[:, None])
        planar = similarity_2d(xy, valid, rest, rigid)
        similarity = {"params": planar["params"], "residual_px": planar["residual_px"], "valid": planar["frame_valid"] & frame_ok}

        R_pose, t_pose = fit["R"], fit["t"]
        if params["pose_rotation"] == "landmarker":
            shown = rigid[valid[reference, rigid]]
            centre = xyz[reference, shown].mean(axis=0)
            R_pose, t_pose = landmarker_head_motion(
                np.asarray(marks["matrix"])[held], reference, R_pose, fit["s"], t_pose, centre
            )
        pose = {
            "R": R_pose,
            "rvec": rodrigues_vector(R_pose),
            "tvec": t_pose,
            "scale": fit["s"],
            "reproj_err_px": fit["residual_px"],
            "valid": frame_valid,
            "ypr_deg": ypr_yxz(R_pose),
            "neutral_frame": np.array(reference),
        }
        return {"displacements": displacements, "similarity": similarity, "pose": pose}

    def _log_reference(
        self,
        ctx: Context,
        reference: int,
        estimate: NeutralEstimate | None,
        marks: Mapping[str, np.ndarray],
        params: Mapping[str, Any],
        names: np.ndarray,
    ) -> None:
        """The console's line on the reference: a named frame, or the estimate and its head frame;
        a warning when the head frame is turned, when a named frame is expressive, or when an eye
        is never open (no open level to measure its closure from)."""
        angle = float(head_angle_deg(np.asarray(marks["matrix"], np.float64)[[reference], :3, :3])[0])
        score = float(expressiveness(np.asarray(marks["blendshapes"])[[reference]], marks["blendshape_names"])[0])
        if estimate is None:
            ctx.log.log(
                SUMMARY,
                "%s: reference (neutral): frame %d as set (head turned %.1f deg, expressiveness %.2f)",
                self.name,
                reference,
                angle,
                score,
            )
            if angle > float(params["warn_angle_deg"]) or score > float(params["warn_expression"]):
                ctx.log.warning(
                    "%s: the reference frame %d set by neutral_frame is not a frontal neutral face (head "
                    "turned %.1f deg, expressiveness %.2f); neutral_frame=-1 estimates the neutral from "
                    "the whole clip",
                    self.name,
                    reference,
                    angle,
                    score,
                )
            return
        per_region = ", ".join(f"{region} {len(frames)}" for region, frames in estimate.frames.items() if region != REST)
        ctx.log.log(
            SUMMARY,
            "%s: reference (neutral) estimated from the clip, each region from its least active "
            "frames (%s); head frame %d (turned %.1f deg); nearest single frame %d",
            self.name,
            per_region,
            reference,
            angle,
            estimate.nearest_frame,
        )
        if angle > float(params["warn_angle_deg"]):
            ctx.log.warning(
                "%s: the most frontal frame of the clip, %d, is turned %.1f deg: displacements are "
                "measured in a turned head frame",
                self.name,
                reference,
                angle,
            )
        for eye, known in estimate.eye_open_known.items():
            if not known:
                ctx.log.warning(
                    "%s: the %s eye is shut or nearly shut in every frame: there is no open level to "
                    "measure its closure from; it is mapped against a typical open eye",
                    self.name,
                    "image-left" if eye == "eye_l" else "image-right",
                )
