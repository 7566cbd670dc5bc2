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

The reference frame is chosen, not assumed (:func:`choose_reference`): the most frontal, least
expressive frame near the start of the clip, from the landmarker's blendshapes and head matrix.
Its inner lips are closed before the displacements are taken (:func:`close_reference_lips`), so a
reference with the lips slightly apart does not cost the target that much of its mouth opening.

Coordinates: x right, y down (px, origin at the centre of the top-left pixel), z away from the
camera (px): a right-handed camera frame as OpenCV's. Angles: ``R = Ry(yaw) Rx(pitch) Rz(roll)``,
degrees; yaw about the image's vertical axis, pitch about its horizontal axis, roll in the image
plane.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from runner.stage import Context, Param, SequenceStage, StageError
from stages.geometry.camera import rotation_vector
from stages.geometry.compensate import compensate as similarity_2d
from stages.geometry.signals import expression_signals
from stages.geometry.subset import named_columns

#: Points of the zhang134 layout that move with the skull: eye corners, nose bridge, forehead,
#: temples and the contour beside the eyes (the jaw's contour points move with the mouth).
RIGID_POINTS = (
    "eye_l_0", "eye_l_6", "eye_r_0", "eye_r_6", "nose_bridge_0", "nose_bridge_1", "nose_bridge_2",
    "forehead_l", "forehead_c", "forehead_r", "temple_l", "temple_r", "contour_0", "contour_16",
)

#: The facing inner-lip pairs of the zhang134 layout (upper, lower), left to right, with the teeth
#: edges that lie between them (``teeth_upper_k`` / ``teeth_lower_k`` are mixes of pair k's lips:
#: ``stages/layouts/zhang134_mediapipe.yaml``), for :func:`close_reference_lips`.
LIP_PAIRS = tuple((f"mouth_inner_{k + 1}", f"mouth_inner_{9 - k}", f"teeth_upper_{k}", f"teeth_lower_{k}")
                  for k in range(4))

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


def compensate_rigid3d(xyz: np.ndarray, valid: np.ndarray, reference: int, rigid: np.ndarray, *,
                       huber_px: float = 2.0, iterations: int = 5) -> dict[str, np.ndarray]:
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


def nearest_valid(valid: np.ndarray) -> np.ndarray:
    """``(T,)`` bool -> ``(T,)`` int: each frame's nearest valid frame (itself when valid)."""
    good = np.flatnonzero(valid)
    return good[np.abs(np.arange(len(valid))[:, None] - good[None]).argmin(axis=1)]


def euler_yaw_pitch_roll(R: np.ndarray) -> np.ndarray:
    """``(T, 3, 3)`` rotations -> ``(T, 3)`` degrees (yaw, pitch, roll), ``R = Ry Rx Rz``."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_euler("YXZ", degrees=True)


def expressiveness(blendshapes: np.ndarray, names: np.ndarray) -> np.ndarray:
    """``(T, 52)`` blendshape scores -> ``(T,)``: the sum of the scores of the expression
    blendshapes (all but ``_neutral`` and the gaze directions ``eyeLook*``)."""
    keep = np.array([not str(n).startswith(_NOT_EXPRESSION) for n in names])
    return np.asarray(blendshapes, np.float64)[:, keep].sum(axis=1)


def choose_reference(blendshapes: np.ndarray, names: np.ndarray, matrix: np.ndarray, mouth_open: np.ndarray,
                     valid: np.ndarray, *, search_frames: int, degrees_weight: float = 0.05,
                     mouth_weight: float = 10.0) -> int:
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
    candidates = np.flatnonzero(valid)[:max(1, search_frames)]
    if candidates.size == 0:
        raise ValueError("no frame with a face to take as the reference")
    angle = head_angle_deg(np.asarray(matrix, np.float64)[candidates, :3, :3])
    cost = (expressiveness(np.asarray(blendshapes)[candidates], names) + degrees_weight * angle
            + mouth_weight * np.clip(np.asarray(mouth_open, np.float64)[candidates], 0, None))
    return int(candidates[np.nanargmin(cost)])


def head_angle_deg(R: np.ndarray) -> np.ndarray:
    """``(T, 3, 3)`` rotations (scaled rotations allowed) -> ``(T,)`` rotation angles, degrees."""
    R = R / np.cbrt(np.linalg.det(R))[:, None, None]
    cos = np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1, 1)
    return np.degrees(np.arccos(cos))


class CompensateRigid3D(SequenceStage):
    """``compensate.rigid3d``: head motion removed by 3D alignment of the landmarker's points to a
    chosen reference frame (an extension of Sec. 12 for real footage)."""

    name = "compensate.rigid3d"
    version = "2"
    doc = "reference (neutral) frame chosen from blendshapes and pose; 3D similarity of the rigid points; displacements, pose, 2D similarity"
    inputs = {"points": "points", "landmarks": "landmarks"}
    outputs = {"displacements": "displacements", "similarity": "similarity", "pose": "pose"}
    params = (
        Param("neutral_frame", int, -1, "the reference (neutral) frame; -1: chosen as the most frontal, least "
              "expressive frame among the first search_frames", min=-1, max=10_000_000),
        Param("search_frames", int, 125, "frames searched for the reference (from the first frame with a face)", min=1, max=10_000_000),
        Param("rigid_points", list, list(RIGID_POINTS), "layout points aligned in 3D (they move with the skull)"),
        Param("huber_px", float, 2.0, "Huber threshold of the robust 3D fit, px", min=0.01, max=1000.0),
        Param("warn_angle_deg", float, 12.0, "warn when the reference frame's head is turned more than this", min=0.0, max=180.0),
        Param("warn_expression", float, 2.0, "warn when the reference frame's expressiveness (sum of blendshapes) "
              "exceeds this", min=0.0, max=100.0),
        Param("close_lips", bool, True, "displacements from the reference with its inner lips closed (a reference "
              "with the lips apart would cost the target that much mouth opening)"),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
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
        reference = int(params["neutral_frame"])
        if reference >= n_frames or (reference >= 0 and not frame_ok[reference]):
            raise StageError(f"{self.name}: neutral_frame={reference}: the clip has {n_frames} frames and that "
                             "frame must show the face")
        try:
            if reference < 0:
                mouth = expression_signals(xy, names)["mouth_open"]
                reference = choose_reference(marks["blendshapes"], marks["blendshape_names"], marks["matrix"], mouth,
                                             frame_ok, search_frames=int(params["search_frames"]))
            rigid = named_columns(names, tuple(params["rigid_points"]))
            # Frames without a face hold the nearest frame with one: the target keeps that expression
            # (displacements valid, ``held`` True) while the points and pose stay flagged invalid.
            held = nearest_valid(frame_ok)
            xy, valid = xy[held], valid[held]
            xyz = np.concatenate([xy, np.asarray(points["z"], np.float64)[held][..., None]], axis=-1)
            fit = compensate_rigid3d(xyz, valid, reference, rigid, huber_px=float(params["huber_px"]))
        except (KeyError, ValueError) as exc:
            raise StageError(f"{self.name}: {exc}") from None
        self._warn_reference(ctx, reference, marks, params)
        frame_valid = fit["frame_valid"] & frame_ok
        d_valid = valid & valid[reference][None] & fit["frame_valid"][:, None]
        if (~frame_ok).any():
            ctx.log.warning("%s: no face in %d of %d frames; each holds the expression of the nearest frame with "
                            "one", self.name, int((~frame_ok).sum()), n_frames)
        neutral, d = xy[reference].copy(), fit["d"]
        if params["close_lips"]:
            try:
                neutral, d, gap = close_reference_lips(neutral, d, names)
            except KeyError as exc:
                raise StageError(f"{self.name}: close_lips needs the layout point {exc}; set close_lips=false") from None
            if gap > 0:
                ctx.log.info("%s: the reference frame's lips are apart (up to %.1f px): displacements are taken from "
                             "the reference with its lips closed", self.name, gap)
        extra = {k: np.asarray(points[k]) for k in ("fps", "size") if k in points}
        displacements = {"d": d, "valid": d_valid, "names": names, "neutral": neutral,
                         "neutral_frame": np.array(reference), "held": ~frame_ok, **extra}
        planar = similarity_2d(xy, valid, xy[reference], rigid)
        similarity = {"params": planar["params"], "residual_px": planar["residual_px"],
                      "valid": planar["frame_valid"] & frame_ok}

        pose = {"R": fit["R"], "rvec": rotation_vector(fit["R"]), "tvec": fit["t"],
                "scale": fit["s"], "reproj_err_px": fit["residual_px"], "valid": frame_valid,
                "ypr_deg": euler_yaw_pitch_roll(fit["R"]), "neutral_frame": np.array(reference)}
        return {"displacements": displacements, "similarity": similarity, "pose": pose}

    def _warn_reference(self, ctx: Context, reference: int, marks: Mapping[str, np.ndarray],
                        params: Mapping[str, Any]) -> None:
        """One warning line when the reference frame is turned or expressive."""
        angle = float(head_angle_deg(np.asarray(marks["matrix"], np.float64)[[reference], :3, :3])[0])
        score = float(expressiveness(np.asarray(marks["blendshapes"])[[reference]], marks["blendshape_names"])[0])
        ctx.log.info("%s: reference (neutral) frame %d: head turned %.1f deg, expressiveness %.2f",
                     self.name, reference, angle, score)
        if angle > float(params["warn_angle_deg"]) or score > float(params["warn_expression"]):
            chosen = int(params["neutral_frame"]) >= 0
            advice = ("it is the one neutral_frame names: name another" if chosen
                      else "set neutral_frame=N to choose one")
            ctx.log.warning("%s: the reference (neutral) frame %d is not a frontal neutral face (head turned "
                            "%.1f deg, expressiveness %.2f); %s", self.name, reference, angle, score, advice)
