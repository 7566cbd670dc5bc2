"""The paper's correlation tracker (Sec. 14.1), refined: NCC against a first-frame template
warped by the local motion, Lucas-Kanade sub-pixel refinement, neighbours or a 3D face model
for what a template cannot pin (:class:`NCCTracker`; options in
:class:`stages.geometry.tracker_options.TrackerOptions`)."""

from __future__ import annotations

import numpy as np

from stages.geometry.correlation import carry_along, correlation_peaks, inside, local_affines, sample_patches, intensity
from stages.geometry.face_model import FaceModel, fit_face_model
from stages.geometry.tracker_options import DEFAULTS, TrackerOptions


class NCCTracker:
    """Normalized cross-correlation with a first-frame template warped by the local motion.

    Per frame, for each point: (1) the first-frame template (``template_px`` square, the anchor)
    is warped by the point's local affine motion (:func:`local_affines` of the first-frame
    positions onto the constant-velocity predictions, neighbourhood ``warp_frac`` times the RMS
    spread of the points), which undoes the face's rotation, scale, foreshortening and
    deformation around the point; (2) the warped anchor and the running template (the point's
    patch in the last frame where it was valid) are matched by NCC (``cv2.TM_CCOEFF_NORMED``, luma)
    in a window of side ``template_px + 2 * search_px`` centred on the prediction, and the anchor's
    peak (parabola-refined) is used where its score reaches ``anchor_score`` (no drift), else the
    running template's (appearance the anchor does not have: an open mouth, a silhouette); (3)
    the position is refined against the chosen template by inverse-compositional Lucas-Kanade
    (translation; gain and bias normalized; cells weighted by a Gaussian of ``lk_sigma_px``
    about the centre, where a warped template is least distorted; ``lk_iterations`` steps of at
    most 1 px each); (4) where the template pins the position in one direction only (an edge:
    the hairline), the other direction is taken from the point's neighbours
    (:meth:`with_neighbours`, weight ``prior``, neighbourhood ``prior_frac`` times the spread).
    With a ``face_model`` (:mod:`stages.geometry.face_model`), step (4) is instead a model fit:
    the head pose and expression coefficients that best explain all matches, each weighted by
    its template information, and every point is pulled towards the fitted model's projection
    with weight ``model_prior`` against its match's information times its reliability
    (:meth:`reliability`: a point whose matches have kept close to the model trusts them more)
    (:meth:`with_model`). A textureless point (the nose tip), an
    edge point (the hairline) and a point whose appearance changes under out-of-plane rotation
    then follow the 3D face instead of drifting; an invalid point is placed by the model. The fit
    of each frame is kept in ``fit``.

    A point is valid when the NCC of the final patch with its template reaches ``min_score``, the
    correlation peak-to-sidelobe ratio reaches ``min_psr``, the patch has a standard deviation of
    at least ``min_contrast`` (an occluder or a flat region is not a match) and the template lies
    wholly in the frame. The running template is refreshed at valid points only. An invalid point
    is carried along with the valid points (:func:`carry_along`; with a face model, placed by the
    model), which is also its predicted velocity, so it is found again when it reappears.
    """

    def __init__(self, options: TrackerOptions = DEFAULTS, *, face_model: FaceModel | None = None) -> None:
        self.options = options
        self.face_model = face_model
        self.side = options.template_px
        self.window = (self.side + 2 * options.search_px,) * 2
        grid = np.arange(self.side) - (self.side - 1) / 2.0
        self.lk_weight = np.exp(-(grid[:, None] ** 2 + grid[None, :] ** 2) / (2.0 * options.lk_sigma_px**2))

    def start(self, frame: np.ndarray, xy: np.ndarray) -> None:
        self.first = intensity(frame)
        self.height, self.width = self.first.shape
        self.origin = xy.astype(np.float64).copy()
        spread = np.sqrt(((self.origin - self.origin.mean(axis=0)) ** 2).sum(axis=1).mean())
        self.warp_sigma_px = max(self.options.warp_frac * spread, 1.0)
        self.prior_sigma_px = max(self.options.prior_frac * spread, 1.0)
        self.last = self.origin.copy()
        self.velocity = np.zeros_like(self.last)
        self.trust = np.ones(len(xy))
        self.running = sample_patches(self.first, self.origin, self.side)
        if self.face_model is not None:
            self.fit = self.face_model.first_frame_fit()
            self.noise = np.full(len(xy), self.options.model_noise_px**2)

    def templates(self, dst: np.ndarray, weight: np.ndarray) -> np.ndarray:
        """First-frame templates ``(N, S, S)`` warped by the local affines onto ``dst``."""
        linear, _ = local_affines(self.origin, dst, weight, sigma_px=self.warp_sigma_px)
        return sample_patches(self.first, self.origin, self.side, np.linalg.inv(linear))

    def refine(self, image: np.ndarray, xy: np.ndarray, template: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Inverse-compositional Lucas-Kanade (translation) of ``template (N, S, S)`` from ``xy``;
        returns the refined positions ``(N, 2)``, the final patches and the templates' Hessians
        ``sum w grad T grad T^T / sum w T^2`` ``(N, 2, 2)`` (1/px^2, T zero-mean): how sharply each
        template pins its position in each direction."""
        n = len(xy)
        tz = template - template.mean(axis=(1, 2), keepdims=True)
        gradient = np.stack(np.gradient(tz, axis=(2, 1)), axis=1).reshape(n, 2, -1)  # (N, 2, S*S): d/dx, d/dy
        steepest = gradient * self.lk_weight.reshape(1, 1, -1)
        hessian = steepest @ np.transpose(gradient, (0, 2, 1))  # (N, 2, 2)
        det = hessian[:, 0, 0] * hessian[:, 1, 1] - hessian[:, 0, 1] * hessian[:, 1, 0]
        adjugate = np.stack(
            [np.stack([hessian[:, 1, 1], -hessian[:, 0, 1]], -1), np.stack([-hessian[:, 1, 0], hessian[:, 0, 0]], -1)], -2
        )
        inverse = adjugate / np.where(np.abs(det) > 1e-12, det, np.inf)[:, None, None]  # flat template: no step
        t_std = tz.std(axis=(1, 2))
        tz = tz.reshape(n, -1)
        xy = xy.copy()
        patch = sample_patches(image, xy, self.side)
        for _ in range(self.options.lk_iterations):
            pz = patch.reshape(n, -1) - patch.mean(axis=(1, 2))[:, None]
            error = pz * (t_std / np.maximum(pz.std(axis=1), 1e-6))[:, None] - tz
            xy -= np.clip((inverse @ (steepest @ error[:, :, None]))[:, :, 0], -1.0, 1.0)
            patch = sample_patches(image, xy, self.side)
        energy = (self.lk_weight.reshape(1, -1) * tz * tz).sum(axis=1)
        return xy, patch, hessian / np.maximum(energy, 1e-9)[:, None, None]

    def with_neighbours(self, found: np.ndarray, information: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """Positions ``(N, 2)`` combining each match with where its neighbours' local affine motion
        puts the point: ``(H_i + prior I)^-1 (H_i m_i + prior a_i)``, ``H_i (N, 2, 2)`` the
        template's information (:meth:`refine`), ``m_i`` the match, ``a_i`` the position given by
        :func:`local_affines` of the other points (each weighted by ``ok`` and by how well its own
        template pins it, ``e / (e + prior)`` with ``e`` the smaller eigenvalue of its ``H``). A
        template that pins one direction only, an edge, takes the other from its neighbours."""
        eigen = np.linalg.eigvalsh(information)[:, 0]
        weight = ok * eigen / (eigen + self.options.prior)
        _, around = local_affines(self.origin, found, weight, sigma_px=self.prior_sigma_px, exclude_self=True)
        system = information + self.options.prior * np.eye(2)
        rhs = (information @ found[:, :, None])[:, :, 0] + self.options.prior * around
        return np.linalg.solve(system, rhs[:, :, None])[:, :, 0]

    def with_model(self, found: np.ndarray, information: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """Positions ``(N, 2)`` combining each match with the face model fitted to all matches
        (:func:`fit_face_model` from the last frame's fit): ``(W_i + model_prior I)^-1 (W_i m_i +
        model_prior p_i)``, ``p_i`` the fitted model's projection, ``W_i = q_i H_i`` the template
        information ``H_i`` scaled by the point's reliability ``q_i`` (:meth:`reliability`; 0
        where not ``ok``, so such a point takes ``p_i``). The fit weighs each match by ``H_i``
        alone: the reliability decides only how far a point trusts its own match. (In the fit it
        let a few steady points steer the pose: on held-out performer 11's live clip the pose
        error rose from 1.82 to 2.32 deg.)"""
        weight = information * ok[:, None, None]
        self.fit = fit_face_model(self.face_model, found, weight, self.fit, ridge=self.options.model_ridge)
        weight = weight * self.reliability()[:, None, None]
        residual = ((found - self.fit.xy) ** 2).sum(axis=1)
        rate = self.options.model_noise_rate * ok
        self.noise = (1.0 - rate) * self.noise + rate * residual
        system = weight + self.options.model_prior * np.eye(2)
        rhs = (weight @ found[:, :, None])[:, :, 0] + self.options.model_prior * self.fit.xy
        return np.linalg.solve(system, rhs[:, :, None])[:, :, 0]

    def reliability(self) -> np.ndarray:
        """``q_i = min(model_noise_px^2 / n_i, 4)`` ``(N,)``: how far each point's matches can be
        trusted, from ``n_i`` (px^2), the exponential moving average (rate ``model_noise_rate``,
        over frames where the point was matched) of its squared distance to the fitted model,
        started at ``model_noise_px^2`` (``q = 1``). A point whose template keeps agreeing with the
        face (an eye corner) comes to outweigh the model, up to 4 times; one whose matches wander
        (the hairline along its edge, lips whose look changes as the mouth opens) leans on the
        model instead: an adaptive estimate of each match's noise, as in an adaptive Kalman
        filter's measurement covariance."""
        return np.minimum(self.options.model_noise_px**2 / np.maximum(self.noise, 1e-12), 4.0)

    def step(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        import cv2

        image = intensity(frame)
        predicted = self.last + self.velocity
        centre = np.rint(predicted)
        anchor = self.templates(predicted, self.trust)
        s = self.window[0] - self.side + 1
        response = np.empty((len(centre), s, s), np.float32)
        windows = [cv2.getRectSubPix(image, self.window, (float(cx), float(cy))) for cx, cy in centre]
        for i, window in enumerate(windows):
            response[i] = cv2.matchTemplate(window, anchor[i], cv2.TM_CCOEFF_NORMED)
        score_a = response.reshape(len(centre), -1).max(axis=1)
        use_anchor = score_a >= self.options.anchor_score
        for i in np.flatnonzero(~use_anchor):
            response[i] = cv2.matchTemplate(windows[i], self.running[i], cv2.TM_CCOEFF_NORMED)
        offset, _, psr = correlation_peaks(response)
        found = centre + offset
        template = np.where(use_anchor[:, None, None], anchor, self.running)
        found, patch, information = self.refine(image, found, template)
        pz = patch - patch.mean(axis=(1, 2), keepdims=True)
        tz = template - template.mean(axis=(1, 2), keepdims=True)
        norms = np.linalg.norm(pz, axis=(1, 2)) * np.linalg.norm(tz, axis=(1, 2))
        score = (pz * tz).sum((1, 2)) / np.maximum(norms, 1e-9)
        half = self.side // 2
        o = self.options
        valid = (score >= o.min_score) & (psr >= o.min_psr) & (patch.std(axis=(1, 2)) >= o.min_contrast)
        if self.face_model is not None:
            found = self.with_model(found, information, valid)
        elif self.options.prior > 0:  # score and running template stay those of the match itself
            found = self.with_neighbours(found, information, valid)
        valid &= inside(found - half, self.width - 2 * half, self.height - 2 * half)
        self.running[valid] = patch[valid]
        carried = found if self.face_model is not None else carry_along(self.last, found, valid)
        self.velocity = carried - self.last
        self.last = carried
        self.trust = valid.astype(np.float64)
        return self.last.copy(), valid, np.clip(score, 0.0, 1.0).astype(np.float32)
