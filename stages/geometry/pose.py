"""3D head pose per frame from the rigid feature points (paper Sec. 12.1, eq. 10).

Eq. 10, ``lambda_i m~_i = A P Omega p~_i``, relates the generic 3D face model's points ``p_i``
(head frame, mm) to their images ``m_i`` (px) through the intrinsics ``A`` and the head pose
``Omega = [R t; 0 1]``. Only the rigid points (hairline and inner eye corners) are used. The pose
is found with ``cv2.solvePnP``: SQPnP for the first solvable frame, then Levenberg-Marquardt
(``SOLVEPNP_ITERATIVE``) started from the previous frame's pose, which keeps the sequence
temporally consistent. Optionally the generic model is first fitted to the performer's neutral
(first) frame, taken as frontal, which removes most of the bias of a generic shape. A frame with fewer valid rigid points than ``min_points`` (or where PnP
fails) is flagged invalid and its pose interpolated (slerp for rotation, linear for translation)
from the nearest solved frames; the run continues. Optional Gaussian smoothing over time acts on
sign-aligned quaternions and translations.

With ``model=face`` (an extension beyond the paper) the pose comes instead from *all* tracked
points: eq. 10's generic model is extended by the performer's expression components
(:mod:`stages.geometry.face_model`) and pose and expression are fitted jointly per frame, so the
non-rigid points (brows, lids, mouth) constrain the pose too.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from runner.stage import Context, Param, SequenceStage, StageError
from stages.geometry.bundles import HEAD_POSE_PNP, POINTS
from stages.pack.bundle_types import CAMERA, LAYOUT, PACK_GEOMETRY, PACK_MODEL3D
from stages.geometry.camera import project_pose
from stages.geometry.rotation import rodrigues_vector, rotation_rodrigues
from stages.geometry.face_model import FaceModel, bundle_face_model, fit_face_model
from stages.geometry.frontalize import adapt_to_reference, frontal_translation
from stages.geometry.smooth import gaussian_smooth
from stages.geometry.subset import param_columns, rigid_columns
from stages.pack.bundles import camera_from_bundle, layout_from_bundle, model3d_from_bundle


def default_intrinsics(size: tuple[int, int]) -> np.ndarray:
    """Camera matrix ``A (3, 3)`` for an image of ``size = (W, H)`` px when none is known: focal
    length ``f = max(W, H)`` px (about a 53 degree field of view across the long side), square
    pixels, no skew, principal point at the image centre ``((W - 1) / 2, (H - 1) / 2)``."""
    width, height = size
    f = float(max(width, height))
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def reprojection_error(rvec: np.ndarray, tvec: np.ndarray, model: np.ndarray, image: np.ndarray, camera: np.ndarray) -> float:
    """RMS distance in px between ``image (n, 2)`` and ``model (n, 3)`` projected with the pose."""
    projected = project_pose(model, rotation_rodrigues(rvec), tvec, camera)[0]
    return float(np.sqrt(np.mean(np.sum((projected - image) ** 2, axis=1))))


def adapt_model(model: np.ndarray, image: np.ndarray, camera: np.ndarray) -> np.ndarray:
    """Fit the generic model to the performer's neutral frame, assumed frontal (``R = I``).

    The translation is :func:`frontal_translation`; then each model point is moved parallel to
    the image plane, keeping its depth, so that it projects exactly onto its observation. Poses
    found with the adapted model are relative to that neutral frame.

    Parameters
    ----------
    model : (n, 3) float
        Generic model points, head frame (mm).
    image : (n, 2) float
        Their observations in the neutral frame, px.
    camera : (3, 3) float
        Intrinsic matrix ``A``.

    Returns
    -------
    (n, 3) float64
        The adapted model (same depths ``z``).
    """
    return adapt_to_reference(model, image, np.eye(3), frontal_translation(model, image, camera), camera)


def interpolate_poses(rvec: np.ndarray, tvec: np.ndarray, known: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fill the frames where ``known (T,)`` is False: rotations ``rvec (T, 3)`` by slerp and
    translations ``tvec (T, 3)`` linearly between the nearest known frames, held at the ends."""
    if np.all(known):
        return rvec.copy(), tvec.copy()
    from scipy.spatial.transform import Rotation, Slerp

    frames = np.arange(len(known))
    times = frames[known]
    rvec, tvec = rvec.copy(), tvec.copy()
    if len(times) == 1:
        rvec[:], tvec[:] = rvec[times[0]], tvec[times[0]]
        return rvec, tvec
    slerp = Slerp(times, Rotation.from_rotvec(rvec[known]))
    rvec[~known] = slerp(np.clip(frames[~known], times[0], times[-1])).as_rotvec()
    for k in range(3):
        tvec[:, k] = np.interp(frames, times, tvec[known, k])
    return rvec, tvec


def smooth_poses(rvec: np.ndarray, tvec: np.ndarray, known: np.ndarray, *, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian smoothing over time (:func:`gaussian_smooth`) of the known poses: quaternions made
    sign-continuous, smoothed and renormalized; translations smoothed. Shapes ``(T, 3)``."""
    from scipy.spatial.transform import Rotation

    quat = Rotation.from_rotvec(rvec).as_quat()
    for t in range(1, len(quat)):
        if np.dot(quat[t], quat[t - 1]) < 0:
            quat[t] = -quat[t]
    quat, _ = gaussian_smooth(quat, known, sigma=sigma)
    tvec, _ = gaussian_smooth(tvec, known, sigma=sigma)
    return Rotation.from_quat(quat / np.linalg.norm(quat, axis=1, keepdims=True)).as_rotvec(), tvec


def estimate_poses(
    image: np.ndarray,
    valid: np.ndarray,
    model: np.ndarray,
    camera: np.ndarray,
    *,
    min_points: int = 4,
    smooth_sigma: float = 0.0,
    adapt: bool = False,
) -> dict[str, np.ndarray]:
    """Head pose per frame by PnP (eq. 10) from the rigid points.

    Parameters
    ----------
    image : (T, R, 2) float
        Rigid points in each frame, px.
    valid : (T, R) bool
        Their validity.
    model : (R, 3) float
        The same points on the generic 3D face model, head frame (mm).
    camera : (3, 3) float
        Intrinsic matrix ``A``.
    min_points : int
        Fewest valid rigid points to solve a frame (at least 4).
    smooth_sigma : float
        Temporal Gaussian smoothing of the solved poses, frames (0 = off).
    adapt : bool
        Fit the model to the first frame where all rigid points are valid, taken as the frontal
        neutral (:func:`adapt_model`), before solving.

    Returns
    -------
    dict
        ``rvec (T, 3)``, ``tvec (T, 3)`` (OpenCV convention, model -> camera, ``tvec`` in the
        model's units), ``R (T, 3, 3)``, ``reproj_err_px (T,)`` (RMS over the frame's valid rigid
        points, NaN where none), ``valid (T,)`` (False where the pose was interpolated).
    """
    import cv2

    model = np.ascontiguousarray(model, dtype=np.float64)
    camera = np.asarray(camera, dtype=np.float64)
    n_frames = len(image)
    rvec = np.zeros((n_frames, 3))
    tvec = np.zeros((n_frames, 3))
    solved = np.zeros(n_frames, bool)
    guess: tuple[np.ndarray, np.ndarray] | None = None
    complete = np.flatnonzero(valid.all(axis=1))
    if adapt and len(complete):
        model = adapt_model(model, image[complete[0]], camera)
    for t in range(n_frames):
        use = valid[t]
        if use.sum() < max(min_points, 4):
            continue
        obj, img = model[use], np.ascontiguousarray(image[t, use], dtype=np.float64)
        try:
            if guess is None:
                ok, r, tr = cv2.solvePnP(obj, img, camera, None, flags=cv2.SOLVEPNP_SQPNP)
                guess = (r, tr)
            ok, r, tr = cv2.solvePnP(
                obj,
                img,
                camera,
                None,
                rvec=guess[0].copy(),
                tvec=guess[1].copy(),
                useExtrinsicGuess=True,
                flags=cv2.SOLVEPNP_ITERATIVE,
            )
        except cv2.error:
            continue
        if not ok or not np.isfinite(r).all() or not np.isfinite(tr).all() or tr[2, 0] <= 0:
            continue
        rvec[t], tvec[t], solved[t] = r.ravel(), tr.ravel(), True
        guess = (r, tr)
    if not solved.any():
        raise StageError(f"pose: no frame has {max(min_points, 4)} valid rigid points for PnP")
    if smooth_sigma > 0:
        rvec[solved], tvec[solved] = (x[solved] for x in smooth_poses(rvec, tvec, solved, sigma=smooth_sigma))
    rvec, tvec = interpolate_poses(rvec, tvec, solved)
    error = np.array(
        [
            reprojection_error(rvec[t], tvec[t], model[valid[t]], image[t, valid[t]], camera) if valid[t].any() else np.nan
            for t in range(n_frames)
        ]
    )
    return {"rvec": rvec, "tvec": tvec, "R": rotation_rodrigues(rvec), "reproj_err_px": error, "valid": solved}


def estimate_face_poses(
    image: np.ndarray, valid: np.ndarray, model: FaceModel, *, smooth_sigma: float = 0.0, iterations: int = 10
) -> dict[str, np.ndarray]:
    """Head pose per frame from all tracked points by fitting the face model: eq. 10 with the
    generic model extended by the performer's expression components
    (:func:`stages.geometry.face_model.fit_face_model` on each frame's valid points, unit
    information, started from the previous frame's fit).

    Parameters
    ----------
    image : (T, N, 2) float
        Tracked points, px.
    valid : (T, N) bool
        Their validity; a frame with fewer than 4 valid points is flagged invalid and its pose
        interpolated (:func:`interpolate_poses`).
    model : FaceModel
        The tracked points' model (:func:`stages.geometry.face_model.build_face_model`); poses
        are relative to its frontal first frame.
    smooth_sigma : float
        Temporal Gaussian smoothing of the solved poses, frames (0 = off).

    Returns
    -------
    dict
        As :func:`estimate_poses`; ``reproj_err_px`` is the RMS distance of the valid points to
        the fitted model.
    """
    fit = model.first_frame_fit()
    n_frames = len(image)
    rvec, tvec = np.zeros((n_frames, 3)), np.zeros((n_frames, 3))
    error = np.full(n_frames, np.nan)
    solved = np.asarray(valid, bool).sum(axis=1) >= 4
    if not solved.any():
        raise StageError("pose: no frame has 4 valid points to fit the face model to")
    for t in np.flatnonzero(solved):
        ok = valid[t]
        xy = np.where(ok[:, None], image[t], 0.0)
        fit = fit_face_model(model, xy, np.eye(2)[None] * ok[:, None, None], fit, iterations=iterations)
        rvec[t], tvec[t] = rodrigues_vector(fit.R), fit.t
        error[t] = np.sqrt(np.mean(np.sum((fit.xy - xy)[ok] ** 2, axis=1)))
    if smooth_sigma > 0:
        rvec[solved], tvec[solved] = (x[solved] for x in smooth_poses(rvec, tvec, solved, sigma=smooth_sigma))
    rvec, tvec = interpolate_poses(rvec, tvec, solved)
    return {"rvec": rvec, "tvec": tvec, "R": rotation_rodrigues(rvec), "reproj_err_px": error, "valid": solved}


class PnPPose(SequenceStage):
    """``pose.pnp``: the performer's head pose per frame (Sec. 12.1)."""

    name = "pose.pnp"
    version = "5"
    doc = "3D head pose per frame by PnP from the rigid points and the pack's generic 3D model (eq. 10)"
    inputs = {"points": POINTS, "layout": LAYOUT, "model3d": PACK_MODEL3D, "camera": CAMERA, "geometry": PACK_GEOMETRY}
    optional_inputs = frozenset({"camera", "geometry"})
    outputs = {"pose": HEAD_POSE_PNP}
    params = (
        Param(
            "intrinsics",
            str,
            "pack",
            "camera matrix: the pack's (input 'camera'), or the default from the image "
            "size (f = max(W, H), principal point at the centre)",
            choices=("pack", "image"),
        ),
        Param(
            "focal_px", float, 0.0, "if > 0, focal length in px with the principal point at the image centre", min=0.0, max=1e6
        ),
        Param(
            "model",
            str,
            "rigid",
            "rigid: PnP on the rigid points with the generic model (Sec. 12.1); face: fit "
            "the face model (generic shape plus the pack's captured expressions, input 'geometry') to all "
            "tracked points",
            choices=("rigid", "face"),
        ),
        Param("components", int, 8, "face model: expression components (PCA of the pack's captured geometries)", min=0, max=256),
        Param(
            "points",
            list,
            [],
            "rigid model: names of the points used for PnP; empty: the layout's rigid points "
            "(hairline and inner eye corners, Sec. 12.1)",
            items=str,
        ),
        Param(
            "min_points", int, 4, "fewest valid rigid points to solve a frame (else flagged and interpolated)", min=3, max=1000
        ),
        Param("smooth_sigma", float, 0.0, "temporal Gaussian smoothing of the poses, frames (0 = off)", min=0.0, max=1000.0),
        Param(
            "adapt_model",
            bool,
            True,
            "fit the generic model to the first complete frame, taken as the frontal neutral; poses are then relative to it",
        ),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        params = {p.name: p.default for p in self.params} | dict(params)
        points = inputs["points"]
        try:
            layout = layout_from_bundle(inputs["layout"])
        except ValueError as exc:
            raise StageError(f"{self.name}: input 'layout': {exc}") from None
        min_points = max(int(params["min_points"]), 4)
        if params["points"]:
            columns = param_columns(np.asarray(points["names"]), params["points"], stage=self.name, param="points")
        else:
            columns = rigid_columns(np.asarray(points["names"]), layout, at_least=min_points, stage=self.name)
        camera = self.camera(points, inputs, params)
        if params["model"] == "face":
            if inputs.get("geometry") is None:
                raise StageError(f"{self.name}: model=face needs the input 'geometry' (pack.load's geometry)")
            if not np.asarray(points["valid"][0]).all():
                raise StageError(f"{self.name}: model=face needs every tracked point valid in the first frame")
            try:
                model = bundle_face_model(
                    inputs["model3d"],
                    inputs["geometry"],
                    [str(n) for n in points["names"]],
                    points["xy"][0],
                    columns,
                    camera,
                    components=int(params["components"]),
                )
            except ValueError as exc:
                raise StageError(f"{self.name}: {exc}") from None
            pose = estimate_face_poses(points["xy"], points["valid"], model, smooth_sigma=float(params["smooth_sigma"]))
            return {"pose": {**pose, "camera": camera}}
        names = [str(points["names"][c]) for c in columns]
        try:
            model = model3d_from_bundle(inputs["model3d"], names)
        except ValueError as exc:
            raise StageError(f"{self.name}: input 'model3d': {exc}") from None
        pose = estimate_poses(
            points["xy"][:, columns],
            points["valid"][:, columns],
            model,
            camera,
            min_points=min_points,
            smooth_sigma=float(params["smooth_sigma"]),
            adapt=bool(params["adapt_model"]),
        )
        return {"pose": {**pose, "camera": camera}}

    def camera(self, points: Mapping[str, np.ndarray], inputs: Mapping[str, Any], params: Mapping[str, Any]) -> np.ndarray:
        """The intrinsic matrix chosen by the ``intrinsics`` and ``focal_px`` parameters."""
        focal = float(params["focal_px"])
        if params["intrinsics"] == "pack" and focal <= 0:
            if inputs.get("camera") is None:
                raise StageError(f"{self.name}: intrinsics=pack needs the input 'camera' (pack.load's camera)")
            size = tuple(int(v) for v in points["size"]) if "size" in points else None
            try:
                return camera_from_bundle(inputs["camera"], size=size)
            except ValueError as exc:
                raise StageError(f"{self.name}: input 'camera': {exc} or intrinsics=image (and focal_px)") from None
        if "size" not in points:
            raise StageError(f"{self.name}: the points carry no image size; use intrinsics=pack")
        camera = default_intrinsics(tuple(int(v) for v in points["size"]))
        if focal > 0:
            camera[0, 0] = camera[1, 1] = focal
        return camera
