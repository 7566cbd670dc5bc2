"""Feature point tracking in a performer clip (paper Sec. 14.1: "correlation-based tracking").

The default tracker (``method="ncc"``) follows each point of the tracked subset with normalized
cross-correlation (NCC) of a small template inside a search window centred on a constant-velocity
prediction and controls drift by matching the first-frame template (the anchor), warped by the
point's local affine motion estimated from its neighbours, in the same window: where the anchor
matches well its peak wins, else the running template's. The peak is refined to sub-pixel
precision by a parabola, then by inverse-compositional Lucas-Kanade; a point whose template pins
one direction only (an edge, e.g. the hairline) takes the other from its neighbours -- or, given
the performer pack, every point is pulled towards a 3D face model (generic shape plus the
performer's captured expressions) fitted to all matches each frame. Every point
in every frame gets a confidence (the final NCC). A point that is lost or leaves the frame is
flagged invalid, carried along by the similarity motion of the valid points, and keeps being
searched for; it is never dropped.

``method`` also selects OpenCV's correlation-filter trackers (``csrt``, ``kcf``, ``mosse``, one
tracker per point on a box around it) and pyramidal Lucas-Kanade with a forward-backward check
(``lk``), so that a benchmark can compare them on the same clip.

Frames are consumed one at a time from an iterable; a clip is never held in memory.
"""

from __future__ import annotations

import csv
import functools
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping

import numpy as np

from runner.stage import Context, Param, SequenceStage, StageError
from stages.geometry.compensate import apply_similarity, fit_similarity
from stages.geometry.face_model import FaceModel, bundle_face_model, fit_face_model
from stages.geometry.subset import rigid_columns
from stages.layout import load_layout
from stages.pack.bundles import camera_from_bundle

METHODS = ("ncc", "csrt", "kcf", "mosse", "lk")
FACE_MODEL_INPUTS = ("model3d", "geometry", "camera")  # pack.load's bundles of the performer pack


@dataclass
class Tracks:
    """Tracked trajectories of N points over T frames.

    Attributes
    ----------
    xy : (T, N, 2) float64
        Positions in px (x right, y down, origin at the centre of the top-left pixel). For an
        invalid entry, the tracker's best guess (``ncc``: the last valid position carried along
        with the valid points; other methods: the last valid position).
    valid : (T, N) bool
        True where the tracker is confident the point was found inside the frame.
    confidence : (T, N) float32
        In [0, 1]: NCC of the patch found with its template (``ncc``), forward-backward
        agreement ``exp(-e / fb_px)`` (``lk``), 1 or 0 as reported by the OpenCV tracker
        (``csrt``, ``kcf``, ``mosse``).
    """

    xy: np.ndarray
    valid: np.ndarray
    confidence: np.ndarray


def to_gray(frame: np.ndarray) -> np.ndarray:
    """An ``(H, W)``, ``(H, W, 1)`` or RGB ``(H, W, 3)`` frame as an ``(H, W)`` float32 image in
    the frame's own intensity units."""
    import cv2
    if frame.ndim == 3 and frame.shape[2] == 3:
        frame = cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2GRAY)
    elif frame.ndim == 3:
        frame = frame[..., 0]
    return np.asarray(frame, dtype=np.float32)


def inside(xy: np.ndarray, width: int, height: int) -> np.ndarray:
    """``(..., 2)`` positions -> ``(...)`` bool, True for positions on the image ``[0, W-1] x [0, H-1]``."""
    return (xy[..., 0] >= 0) & (xy[..., 0] <= width - 1) & (xy[..., 1] >= 0) & (xy[..., 1] <= height - 1)


def correlation_peaks(response: np.ndarray, *, exclude: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel peaks, peak values and peak-to-sidelobe ratios of a stack of correlation surfaces.

    Parameters
    ----------
    response : (N, S, S) float
        Correlation surfaces (e.g. ``cv2.TM_CCOEFF_NORMED`` outputs); cell ``(j, i)`` is the score
        of a displacement ``(i - (S-1)/2, j - (S-1)/2)`` px from the window centre.
    exclude : int
        Half-size of the square around the peak left out of the sidelobe (MOSSE's PSR).

    Returns
    -------
    offset : (N, 2) float64
        Peak displacement ``(dx, dy)`` in px from the window centre; the sub-pixel part comes from
        a parabola through the peak and its two neighbours along each axis (zero on the border).
    peak : (N,) float64
        Peak value.
    psr : (N,) float64
        ``(peak - mean(sidelobe)) / std(sidelobe)``.
    """
    n, s, _ = response.shape
    flat = response.reshape(n, s * s).astype(np.float64)
    arg = flat.argmax(axis=1)
    py, px = np.divmod(arg, s)
    rows = np.arange(n)
    peak = flat[rows, arg]

    def parabola(minus: np.ndarray, plus: np.ndarray, at_edge: np.ndarray) -> np.ndarray:
        curvature = minus - 2.0 * peak + plus
        ok = (~at_edge) & (curvature < 0)
        shift = np.where(ok, 0.5 * (minus - plus) / np.where(ok, curvature, -1.0), 0.0)
        return np.clip(shift, -0.5, 0.5)

    surface = response.astype(np.float64)
    edge_x = (px == 0) | (px == s - 1)
    edge_y = (py == 0) | (py == s - 1)
    sub_x = parabola(surface[rows, py, np.maximum(px - 1, 0)], surface[rows, py, np.minimum(px + 1, s - 1)], edge_x)
    sub_y = parabola(surface[rows, np.maximum(py - 1, 0), px], surface[rows, np.minimum(py + 1, s - 1), px], edge_y)
    centre = (s - 1) / 2.0
    offset = np.stack([px - centre + sub_x, py - centre + sub_y], axis=1)

    grid = np.arange(s)
    near = (np.abs(grid[None, :, None] - py[:, None, None]) <= exclude) & (
        np.abs(grid[None, None, :] - px[:, None, None]) <= exclude
    )
    side = ~near.reshape(n, s * s)
    count = side.sum(axis=1)
    mean = (flat * side).sum(axis=1) / count
    var = (((flat - mean[:, None]) ** 2) * side).sum(axis=1) / count
    psr = (peak - mean) / (np.sqrt(var) + 1e-6)
    return offset, peak, psr


def carry_along(last: np.ndarray, found: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """New positions ``(N, 2)``: ``found`` where ``valid``; elsewhere ``last`` moved by the 2D
    similarity (eq. 8-9) that best maps the valid points' ``last`` onto their ``found`` (the head's
    motion), by their translation if only one is valid, not at all if none is."""
    if valid.sum() >= 2:
        moved = apply_similarity(fit_similarity(last[valid], found[valid]), last)
    elif valid.any():
        moved = last + (found[valid] - last[valid])
    else:
        moved = last
    return np.where(valid[:, None], found, moved)


def local_affines(src: np.ndarray, dst: np.ndarray, weight: np.ndarray, *, sigma_px: float,
                  ridge: float = 0.05, exclude_self: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Local affine motions of N points: linear parts ``M_i (N, 2, 2)`` and positions ``b_i (N, 2)``.

    For each point ``i``, the affine ``y = M_i (x - src_i) + b_i`` minimizing
    ``sum_j w_ij |M_i (src_j - src_i) + b_i - dst_j|^2 + lambda_i |M_i - M_g|_F^2`` with
    ``w_ij = weight_j exp(-|src_j - src_i|^2 / (2 sigma_px^2))`` (the point's neighbourhood on the
    face), ``lambda_i = ridge * sigma_px^2 * sum_j w_ij`` and ``M_g`` the linear part of the
    unweighted affine fit of all points with ``weight > 0`` (the identity with fewer than 3; pulled
    faintly towards it, so that collinear points give a finite answer), so a
    point with few or collinear neighbours falls back on the face's global motion. With
    ``exclude_self`` the sum leaves ``j = i`` out: ``b_i`` is then where the neighbours alone put
    point ``i``.

    Parameters
    ----------
    src, dst : (N, 2) float
        Positions in the first and in the current frame, px.
    weight : (N,) float
        Trust in each correspondence (0 = unused).
    """
    x = np.column_stack([src, np.ones(len(src))])
    use = weight > 0
    m_global = np.eye(2)
    if use.sum() >= 3:  # least squares, a faint pull to the identity where the points are collinear
        pull = 1e-6 * use.sum() * (src[use].var(axis=0).sum() + 1.0)
        gram = x[use].T @ x[use] + pull * np.diag([1.0, 1.0, 0.0])
        m_global = np.linalg.solve(gram, x[use].T @ dst[use] + pull * np.eye(3, 2))[:2].T
    rel = src[None, :, :] - src[:, None, :]                              # (N, N, 2): src_j - src_i
    w = weight[None, :] * np.exp(-(rel ** 2).sum(axis=2) / (2.0 * sigma_px ** 2))
    if exclude_self:
        np.fill_diagonal(w, 0.0)
    design = np.concatenate([rel, np.ones(rel.shape[:2] + (1,))], axis=2)  # (N, N, 3)
    weighted = np.transpose(design * w[:, :, None], (0, 2, 1))            # (N, 3, N)
    gram = weighted @ design
    rhs = weighted @ dst
    lam = ridge * sigma_px ** 2 * w.sum(axis=1)
    gram[:, 0, 0] += lam
    gram[:, 1, 1] += lam
    rhs[:, :2, :] += lam[:, None, None] * m_global.T[None]
    gram[:, 2, 2] += 1e-9
    solution = np.linalg.solve(gram, rhs)
    return np.transpose(solution[:, :2, :], (0, 2, 1)), solution[:, 2, :]


@functools.lru_cache(maxsize=8)
def patch_grid(side: int) -> np.ndarray:
    """Offsets ``(2, side * side)`` px (x row, y row) of the cells of a square patch from its centre,
    row by row."""
    grid = np.arange(side, dtype=np.float32) - (side - 1) / 2.0
    return np.stack([np.tile(grid, side), np.repeat(grid, side)])


def sample_patches(image: np.ndarray, centres: np.ndarray, side: int, linear: np.ndarray | None = None
                   ) -> np.ndarray:
    """Square patches ``(N, side, side)`` float32 of ``image`` (bicubic, replicated border): patch
    cell ``(r, c)`` of point ``n`` is the image at ``centres[n] + linear[n] @ (c - h, r - h)``,
    ``h = (side - 1) / 2`` (``linear (N, 2, 2)``: identity if omitted)."""
    import cv2
    ux, uy = patch_grid(side)
    cx, cy = centres.astype(np.float32).T
    if linear is None:
        map_x, map_y = cx[:, None] + ux, cy[:, None] + uy
    else:
        m = linear.astype(np.float32)
        map_x = cx[:, None] + m[:, 0, :1] * ux + m[:, 0, 1:] * uy
        map_y = cy[:, None] + m[:, 1, :1] * ux + m[:, 1, 1:] * uy
    patches = cv2.remap(image, map_x.reshape(-1, side), map_y.reshape(-1, side), cv2.INTER_CUBIC,
                        borderMode=cv2.BORDER_REPLICATE)
    return patches.reshape(-1, side, side)


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

    def __init__(self, *, template_px: int = 15, search_px: int = 8, min_score: float = 0.7,
                 min_psr: float = 0.0, min_contrast: float = 2.0, warp_frac: float = 0.3,
                 lk_iterations: int = 2, anchor_score: float = 0.9, prior: float = 0.03,
                 prior_frac: float = 1.5, lk_sigma_px: float = 2.0, face_model: FaceModel | None = None,
                 model_prior: float = 1.0, model_ridge: float = 1.0, model_noise_px: float = 3.0,
                 model_noise_rate: float = 0.2) -> None:
        self.face_model = face_model
        self.model_prior = model_prior
        self.model_ridge = model_ridge
        self.model_noise_px = model_noise_px
        self.model_noise_rate = model_noise_rate
        self.anchor_score = anchor_score
        self.prior = prior
        self.side = template_px
        self.window = (template_px + 2 * search_px, template_px + 2 * search_px)
        self.min_score = min_score
        self.min_psr = min_psr
        self.min_contrast = min_contrast
        self.warp_frac = warp_frac
        self.prior_frac = prior_frac
        self.lk_iterations = lk_iterations
        grid = np.arange(template_px) - (template_px - 1) / 2.0
        self.lk_weight = np.exp(-(grid[:, None] ** 2 + grid[None, :] ** 2) / (2.0 * lk_sigma_px ** 2))

    def start(self, frame: np.ndarray, xy: np.ndarray) -> None:
        self.first = to_gray(frame)
        self.height, self.width = self.first.shape
        self.origin = xy.astype(np.float64).copy()
        spread = np.sqrt(((self.origin - self.origin.mean(axis=0)) ** 2).sum(axis=1).mean())
        self.warp_sigma_px = max(self.warp_frac * spread, 1.0)
        self.prior_sigma_px = max(self.prior_frac * spread, 1.0)
        self.last = self.origin.copy()
        self.velocity = np.zeros_like(self.last)
        self.trust = np.ones(len(xy))
        self.running = sample_patches(self.first, self.origin, self.side)
        if self.face_model is not None:
            self.fit = self.face_model.first_frame_fit()
            self.noise = np.full(len(xy), self.model_noise_px ** 2)

    def templates(self, dst: np.ndarray, weight: np.ndarray) -> np.ndarray:
        """First-frame templates ``(N, S, S)`` warped by the local affines onto ``dst``."""
        linear, _ = local_affines(self.origin, dst, weight, sigma_px=self.warp_sigma_px)
        return sample_patches(self.first, self.origin, self.side, np.linalg.inv(linear))

    def refine(self, image: np.ndarray, xy: np.ndarray, template: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Inverse-compositional Lucas-Kanade (translation) of ``template (N, S, S)`` from ``xy``;
        returns the refined positions ``(N, 2)``, the final patches and the templates' Hessians
        ``sum w grad T grad T^T / sum w T^2`` ``(N, 2, 2)`` (1/px^2, T zero-mean): how sharply each
        template pins its position in each direction."""
        n = len(xy)
        tz = template - template.mean(axis=(1, 2), keepdims=True)
        gradient = np.stack(np.gradient(tz, axis=(2, 1)), axis=1).reshape(n, 2, -1)   # (N, 2, S*S): d/dx, d/dy
        steepest = gradient * self.lk_weight.reshape(1, 1, -1)
        hessian = steepest @ np.transpose(gradient, (0, 2, 1))                          # (N, 2, 2)
        det = hessian[:, 0, 0] * hessian[:, 1, 1] - hessian[:, 0, 1] * hessian[:, 1, 0]
        adjugate = np.stack([np.stack([hessian[:, 1, 1], -hessian[:, 0, 1]], -1),
                             np.stack([-hessian[:, 1, 0], hessian[:, 0, 0]], -1)], -2)
        inverse = adjugate / np.where(np.abs(det) > 1e-12, det, np.inf)[:, None, None]  # flat template: no step
        t_std = tz.std(axis=(1, 2))
        tz = tz.reshape(n, -1)
        xy = xy.copy()
        patch = sample_patches(image, xy, self.side)
        for _ in range(self.lk_iterations):
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
        weight = ok * eigen / (eigen + self.prior)
        _, around = local_affines(self.origin, found, weight, sigma_px=self.prior_sigma_px, exclude_self=True)
        system = information + self.prior * np.eye(2)
        rhs = (information @ found[:, :, None])[:, :, 0] + self.prior * around
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
        self.fit = fit_face_model(self.face_model, found, weight, self.fit, ridge=self.model_ridge)
        weight = weight * self.reliability()[:, None, None]
        residual = ((found - self.fit.xy) ** 2).sum(axis=1)
        rate = self.model_noise_rate * ok
        self.noise = (1.0 - rate) * self.noise + rate * residual
        system = weight + self.model_prior * np.eye(2)
        rhs = (weight @ found[:, :, None])[:, :, 0] + self.model_prior * self.fit.xy
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
        return np.minimum(self.model_noise_px ** 2 / np.maximum(self.noise, 1e-12), 4.0)

    def step(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        import cv2
        image = to_gray(frame)
        predicted = self.last + self.velocity
        centre = np.rint(predicted)
        anchor = self.templates(predicted, self.trust)
        s = self.window[0] - self.side + 1
        response = np.empty((len(centre), s, s), np.float32)
        windows = [cv2.getRectSubPix(image, self.window, (float(cx), float(cy))) for cx, cy in centre]
        for i, window in enumerate(windows):
            response[i] = cv2.matchTemplate(window, anchor[i], cv2.TM_CCOEFF_NORMED)
        score_a = response.reshape(len(centre), -1).max(axis=1)
        use_anchor = score_a >= self.anchor_score
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
        valid = (score >= self.min_score) & (psr >= self.min_psr) & (patch.std(axis=(1, 2)) >= self.min_contrast)
        if self.face_model is not None:
            found = self.with_model(found, information, valid)
        elif self.prior > 0:  # score and running template stay those of the match itself
            found = self.with_neighbours(found, information, valid)
        valid &= inside(found - half, self.width - 2 * half, self.height - 2 * half)
        self.running[valid] = patch[valid]
        carried = found if self.face_model is not None else carry_along(self.last, found, valid)
        self.velocity = carried - self.last
        self.last = carried
        self.trust = valid.astype(np.float64)
        return self.last.copy(), valid, np.clip(score, 0.0, 1.0).astype(np.float32)


class LKTracker:
    """Pyramidal Lucas-Kanade (``cv2.calcOpticalFlowPyrLK``) with a forward-backward check (as in
    OpenCV's ``samples/python/lk_track.py``): a point is valid when both passes converge, the
    round trip returns within ``fb_px`` of the start and the point lies in the frame."""

    def __init__(self, *, template_px: int = 15, levels: int = 2, fb_px: float = 1.0) -> None:
        import cv2
        self.params = dict(
            winSize=(template_px, template_px),
            maxLevel=levels,
            criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01),
        )
        self.fb_px = fb_px

    @staticmethod
    def _gray8(frame: np.ndarray) -> np.ndarray:
        return np.clip(np.rint(to_gray(frame)), 0, 255).astype(np.uint8)

    def start(self, frame: np.ndarray, xy: np.ndarray) -> None:
        self.previous = self._gray8(frame)
        self.last = xy.astype(np.float64).copy()

    def step(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        import cv2
        gray = self._gray8(frame)
        p0 = self.last.astype(np.float32).reshape(-1, 1, 2)
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(self.previous, gray, p0, None, **self.params)
        p0r, st0, _ = cv2.calcOpticalFlowPyrLK(gray, self.previous, p1, None, **self.params)
        p1 = p1.reshape(-1, 2).astype(np.float64)
        error = np.linalg.norm(p0r.reshape(-1, 2) - self.last, axis=1)
        valid = (st1.ravel() == 1) & (st0.ravel() == 1) & (error <= self.fb_px)
        valid &= inside(p1, gray.shape[1], gray.shape[0])
        self.last = np.where(valid[:, None], p1, self.last)
        self.previous = gray
        return self.last.copy(), valid, np.exp(-error / self.fb_px).astype(np.float32)


def _cv2() -> Any:
    """OpenCV, imported when first used (importing it costs start-up time)."""
    import cv2

    return cv2


class OpenCVTracker:
    """One OpenCV single-object tracker (CSRT, KCF or legacy MOSSE) per point, on a
    ``box_px``-square box centred on the point; the point is the box centre plus the first
    frame's sub-pixel offset. ``valid`` is the tracker's success flag and the point in frame."""

    FACTORIES: dict[str, Callable[[], Any]] = {
        "csrt": lambda: _cv2().TrackerCSRT_create(),
        "kcf": lambda: _cv2().TrackerKCF_create(),
        "mosse": lambda: _cv2().legacy.TrackerMOSSE_create(),
    }

    def __init__(self, method: str, *, box_px: int = 31) -> None:
        self.factory = self.FACTORIES[method]
        self.half = box_px // 2

    @staticmethod
    def rgb(frame: np.ndarray) -> np.ndarray:
        """The frame as a contiguous 3-channel image (gray frames repeated)."""
        gray = frame.ndim == 2 or frame.shape[2] == 1
        return np.ascontiguousarray(np.repeat(frame.reshape(frame.shape[:2] + (1,)), 3, axis=2) if gray else frame)

    def start(self, frame: np.ndarray, xy: np.ndarray) -> None:
        image = self.rgb(frame)
        self.height, self.width = image.shape[:2]
        corner = np.rint(xy) - self.half
        self.offset = xy - np.rint(xy)
        self.trackers = []
        side = 2 * self.half + 1
        for cx, cy in corner:
            tracker = self.factory()
            tracker.init(image, (int(cx), int(cy), side, side))
            self.trackers.append(tracker)
        self.last = xy.astype(np.float64).copy()

    def step(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        image = self.rgb(frame)
        valid = np.zeros(len(self.trackers), bool)
        found = self.last.copy()
        for i, tracker in enumerate(self.trackers):
            ok, box = tracker.update(image)
            if ok:
                found[i] = (box[0] + (box[2] - 1) / 2.0, box[1] + (box[3] - 1) / 2.0) + self.offset[i]
                valid[i] = True
        valid &= inside(found, self.width, self.height)
        self.last = np.where(valid[:, None], found, self.last)
        return self.last.copy(), valid, valid.astype(np.float32)


def make_tracker(method: str, *, template_px: int = 15, search_px: int = 8, min_score: float = 0.7,
                 min_psr: float = 0.0, min_contrast: float = 2.0, warp_frac: float = 0.3,
                 lk_iterations: int = 2, anchor_score: float = 0.9, prior: float = 0.03,
                 prior_frac: float = 1.5, lk_sigma_px: float = 2.0, fb_px: float = 1.0,
                 face_model: FaceModel | None = None, model_prior: float = 1.0, model_ridge: float = 1.0,
                 model_noise_px: float = 3.0, model_noise_rate: float = 0.2):
    """The tracker object for ``method`` (one of :data:`METHODS`), configured from the options
    that apply to it (``template_px`` sets the LK window and, with ``search_px``, the box of the
    OpenCV trackers)."""
    if method == "ncc":
        return NCCTracker(template_px=template_px, search_px=search_px, min_score=min_score, min_psr=min_psr,
                          min_contrast=min_contrast, warp_frac=warp_frac, lk_iterations=lk_iterations,
                          anchor_score=anchor_score, prior=prior, prior_frac=prior_frac, lk_sigma_px=lk_sigma_px,
                          face_model=face_model, model_prior=model_prior, model_ridge=model_ridge,
                          model_noise_px=model_noise_px, model_noise_rate=model_noise_rate)
    if method == "lk":
        return LKTracker(template_px=template_px, fb_px=fb_px)
    if method in OpenCVTracker.FACTORIES:
        return OpenCVTracker(method, box_px=template_px + 2 * search_px)
    raise ValueError(f"unknown tracking method {method!r}; expected one of {METHODS}")


def track_points(frames: Iterable[np.ndarray], init_xy: np.ndarray, *, method: str = "ncc",
                 progress: Callable[[int], None] = lambda n: None, **options: Any) -> Tracks:
    """Track N points through a clip, frame by frame.

    Parameters
    ----------
    frames : iterable of (H, W, 3) RGB or (H, W) gray images
        The clip in order, consumed one frame at a time.
    init_xy : (N, 2) float
        Positions in the first frame, px.
    method : str
        ``ncc`` (default), ``csrt``, ``kcf``, ``mosse`` or ``lk``.
    progress : callable
        Called with 1 after each frame.
    **options
        Passed to :func:`make_tracker`.

    Returns
    -------
    Tracks
        ``xy (T, N, 2)``, ``valid (T, N)``, ``confidence (T, N)``; frame 0 is ``init_xy``, valid.
    """
    init_xy = np.asarray(init_xy, dtype=np.float64)
    tracker = make_tracker(method, **options)
    xy, valid, confidence = [], [], []
    for t, frame in enumerate(frames):
        if t == 0:
            tracker.start(frame, init_xy)
            found, ok, score = init_xy.copy(), np.ones(len(init_xy), bool), np.ones(len(init_xy), np.float32)
        else:
            found, ok, score = tracker.step(frame)
        xy.append(found)
        valid.append(ok)
        confidence.append(score)
        progress(1)
    if not xy:
        raise StageError("track: the input clip has no frames")
    return Tracks(np.stack(xy), np.stack(valid), np.stack(confidence).astype(np.float32))


def read_first_frame_points(path: Path) -> tuple[list[str], np.ndarray, tuple[int, int] | None]:
    """Read named first-frame positions from a ``.csv`` (header ``name,x,y``) or ``.json`` file
    (``{"names": [...], "xy": [[x, y], ...]}`` or ``{name: [x, y], ...}``, optionally under a
    ``"points"`` key). Returns the names, an ``(N, 2)`` float64 array in px and the size
    ``(W, H)`` of the frame the points were marked on, when the file states it (a CSV comment line
    ``# frame_size: W H`` before the header, or a JSON key ``"frame_size": [W, H]``), else None."""
    path = Path(path)
    if not path.is_file():
        raise StageError(f"first-frame points file not found: {path}")
    frame_size = None
    try:
        if path.suffix.lower() == ".csv":
            lines = path.read_text().splitlines()
            for line in lines:
                key, _, value = line.lstrip("# ").partition(":")
                if line.startswith("#") and key.strip() == "frame_size":
                    frame_size = tuple(int(v) for v in value.split())
            rows = list(csv.DictReader(line for line in lines if not line.startswith("#")))
            names = [row["name"] for row in rows]
            xy = np.array([[float(row["x"]), float(row["y"])] for row in rows], dtype=np.float64)
        elif path.suffix.lower() == ".json":
            data = json.loads(path.read_text())
            if isinstance(data, dict) and "frame_size" in data:
                frame_size = tuple(int(v) for v in data["frame_size"])
            data = data.get("points", data) if isinstance(data, dict) else data
            if isinstance(data, dict) and "names" in data:
                names, xy = list(data["names"]), np.asarray(data["xy"], dtype=np.float64)
            else:
                names, xy = list(data), np.asarray(list(data.values()), dtype=np.float64)
        else:
            raise StageError(f"{path}: first-frame points must be a .csv or .json file")
    except (KeyError, ValueError, TypeError, AttributeError, json.JSONDecodeError) as exc:
        raise StageError(f"{path}: cannot read first-frame points (expected name,x,y): {exc}") from None
    if xy.ndim != 2 or xy.shape != (len(names), 2) or not np.isfinite(xy).all():
        raise StageError(f"{path}: expected one finite (x, y) pair per named point, got shape {xy.shape}")
    if frame_size is not None and len(frame_size) != 2:
        raise StageError(f"{path}: frame_size must be two integers W H, got {frame_size}")
    return [str(n) for n in names], xy, frame_size


def order_by_layout(path: Path, names: list[str], xy: np.ndarray, expected: tuple[str, ...],
                    size: tuple[int, int], frame_size: tuple[int, int] | None = None) -> np.ndarray:
    """Check first-frame points against the layout's tracked subset and the clip's frame size
    ``size = (W, H)`` (and ``frame_size``, the size the file says they were marked on); return
    them ``(N, 2)`` in the layout's order."""
    if frame_size is not None and tuple(frame_size) != tuple(size):
        raise StageError(f"{path}: the points were marked on a {frame_size[0]}x{frame_size[1]} frame, "
                         f"the clip's frames are {size[0]}x{size[1]}")
    if len(set(names)) != len(names):
        raise StageError(f"{path}: duplicate point names")
    missing = [n for n in expected if n not in names]
    extra = [n for n in names if n not in expected]
    if missing or extra:
        raise StageError(
            f"{path}: {len(names)} points do not match the layout's {len(expected)} tracked points"
            f" (missing {missing[:5]}, unknown {extra[:5]})"
        )
    ordered = xy[[names.index(n) for n in expected]]
    outside = ~inside(ordered, *size)
    if outside.any():
        bad = [expected[i] for i in np.flatnonzero(outside)]
        raise StageError(f"{path}: points outside the {size[0]}x{size[1]} frame: {bad[:5]}")
    return ordered


def iter_frames(stream: Any) -> Iterator[np.ndarray]:
    """Frames of a :class:`runner.stage.FrameStream`, one at a time, read chunk by chunk."""
    for _, chunk in stream.chunks():
        yield from chunk


class CorrelationTrack(SequenceStage):
    """``track.correlation``: the tracked subset of the layout through the performer clip.

    ``init`` is the first-frame points file of the tracked points (a ``file`` pipeline input:
    ``name,x,y`` CSV or JSON), read by :func:`read_first_frame_points` and checked against the
    layout's tracked subset and the frame size. ``model3d``, ``geometry`` and ``camera`` (optional,
    together: ``pack.load``'s bundles of the performer's actor pack) give the ``ncc`` tracker its
    face model (:func:`stages.geometry.face_model.bundle_face_model`: the pack's generic 3D model,
    captured expressions and intrinsics, which must be for the clip's frame size).
    """

    name = "track.correlation"
    version = "5"
    doc = "track the layout's tracked subset through a clip (NCC, or CSRT/KCF/MOSSE/LK)"
    inputs = {"frames": "frames", "init": "file", "model3d": "pack_model3d", "geometry": "pack_geometry",
              "camera": "camera"}
    optional_inputs = frozenset(FACE_MODEL_INPUTS)
    outputs = {"points": "points"}
    params = (
        Param("layout", str, "zhang134", "layout name or YAML path; its `tracked` subset is followed", file=True),
        Param("method", str, "ncc", "tracker", choices=METHODS),
        Param("template_px", int, 15, "template side in px (LK window; OpenCV trackers' box is template+2*search)"),
        Param("search_px", int, 8, "search radius in px around the constant-velocity prediction"),
        Param("min_score", float, 0.7, "ncc: lowest peak NCC of a valid point"),
        Param("min_psr", float, 0.0, "ncc: lowest peak-to-sidelobe ratio of a valid point (0 = off: NCC peaks "
              "on smooth skin are broad, so their PSR is low even when right)"),
        Param("min_contrast", float, 2.0, "ncc: lowest standard deviation (intensity levels) of a valid point's patch"),
        Param("anchor_score", float, 0.9, "ncc: score of the warped first-frame template above which it is used "
              "instead of the running template"),
        Param("warp_frac", float, 0.3, "ncc: neighbourhood (Gaussian sigma) of the local affine motion that warps "
              "a point's first-frame template, as a fraction of the RMS spread of the points"),
        Param("lk_iterations", int, 2, "ncc: inverse-compositional Lucas-Kanade steps of the sub-pixel refinement"),
        Param("lk_sigma_px", float, 2.0, "ncc: Gaussian weight (sigma, px) of the template cells in the Lucas-Kanade "
              "refinement: the centre of a warped template is the least distorted"),
        Param("prior", float, 0.03, "ncc without a pack: weight (1/px^2) of the neighbours' position against the template's own "
              "information (0 = off)"),
        Param("prior_frac", float, 1.5, "ncc: neighbourhood (Gaussian sigma) of the neighbours' position, as a "
              "fraction of the RMS spread of the points"),
        Param("fb_px", float, 1.0, "lk: largest forward-backward error of a valid point, px"),
        Param("model_prior", float, 1.0, "ncc with a pack: weight (1/px^2) of the fitted face model's position "
              "against the template's own information"),
        Param("model_components", int, 8, "ncc with a pack: expression components of the face model (PCA of "
              "the pack's captured geometries)"),
        Param("model_ridge", float, 1.0, "ncc with a pack: weight of the prior keeping the expression "
              "coefficients within the captured set's spread"),
        Param("model_noise_px", float, 3.0, "ncc with a pack: reference match noise, px; a point whose running "
              "RMS distance to the fitted model is below it gains weight against the model (up to 4x), "
              "one above it loses weight"),
        Param("model_noise_rate", float, 0.2, "ncc with a pack: rate of the running mean of each point's squared "
              "distance to the fitted model (0 = fixed weights)"),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        params = {p.name: p.default for p in self.params} | dict(params)
        stream = inputs["frames"]
        info = stream.info
        layout = load_layout(params["layout"])
        expected = tuple(layout.point_names[i] for i in layout.tracked)
        path = Path(inputs["init"])
        names, xy, frame_size = read_first_frame_points(path)
        init = order_by_layout(path, names, xy, expected, (info.width, info.height), frame_size)
        options = {p.name: params[p.name] for p in self.params
                   if p.name not in ("layout", "method", "model_components")}
        given = [port for port in FACE_MODEL_INPUTS if inputs.get(port) is not None]
        if given and len(given) < len(FACE_MODEL_INPUTS):
            raise StageError(f"{self.name}: the face model needs the inputs {', '.join(FACE_MODEL_INPUTS)} together "
                             f"(pack.load's outputs), got only {', '.join(given)}")
        if given and params["method"] == "ncc":
            options["face_model"] = self.face_model(inputs, layout, init, (info.width, info.height),
                                                    params["model_components"])
        tracks = track_points(iter_frames(stream), init, method=params["method"],
                              progress=ctx.progress, **options)
        return {
            "points": {
                "xy": tracks.xy,
                "valid": tracks.valid,
                "confidence": tracks.confidence,
                "names": np.array(expected),
                "fps": np.array(info.fps, dtype=np.float64),
                "size": np.array([info.width, info.height], dtype=np.int64),
            }
        }

    def face_model(self, inputs: Mapping[str, Any], layout: Any, init: np.ndarray, size: tuple[int, int],
                   components: int) -> FaceModel:
        """The tracked points' face model from the performer pack's bundles (:func:`bundle_face_model`)."""
        if components < 1:
            raise StageError(f"{self.name}: model_components must be at least 1, got {components}")
        names = [layout.point_names[i] for i in layout.tracked]
        rigid = rigid_columns(np.array(names), layout, at_least=4, stage=self.name)
        try:
            camera = camera_from_bundle(inputs["camera"], size=size)
            return bundle_face_model(inputs["model3d"], inputs["geometry"], names, init, rigid, camera,
                                     components=components)
        except ValueError as exc:
            raise StageError(f"{self.name}: {exc}") from None
