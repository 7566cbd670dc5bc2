"""Motion compensation with a 2D similarity model (paper Sec. 12, eq. 8-9).

Per frame, the similarity ``T(a, b, tx, ty)`` of eq. 8,

    T(x, y) = [[a, -b], [b, a]] @ (x, y) + (tx, ty),

that best maps the neutral face's rigid points ``x_i`` onto the frame's ``x'_i`` in the least
squares sense of eq. 9, ``min sum_i ||T(x_i) - x'_i||^2``, has a closed form (the 2D case of
Umeyama's / Horn's absolute orientation with scale): with centroids removed,
``a = sum(x . x') / sum |x|^2`` and ``b = sum(x cross x') / sum |x|^2``, then the translation from
the centroids. An optional robust variant reweights the points iteratively with Huber weights.
The head motion is then undone and the displacement ``T^-1(x'_i) - x_i`` of every tracked point
is what feeds expression mapping (Sec. 12).
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from runner.stage import Context, Param, SequenceStage, StageError
from stages.geometry.subset import named_columns, rigid_columns
from stages.layout import load_layout


def fit_similarity(src: np.ndarray, dst: np.ndarray, *, weights: np.ndarray | None = None,
                   huber_px: float | None = None, iterations: int = 10) -> np.ndarray:
    """Least-squares 2D similarity mapping ``src`` onto ``dst`` (eq. 9).

    Parameters
    ----------
    src, dst : (n, 2) float
        Corresponding points in px, ``n >= 2`` (not all coincident).
    weights : (n,) float, optional
        Non-negative weights of the squared residuals (all 1 if omitted).
    huber_px : float, optional
        If given, iteratively reweighted least squares with Huber weights
        ``min(1, huber_px / r_i)`` on the residual lengths ``r_i`` (px), ``iterations`` times.

    Returns
    -------
    (4,) float64
        ``(a, b, tx, ty)`` of eq. 8.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    base = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = base
    for _ in range(1 if huber_px is None else iterations + 1):
        total = w.sum()
        mu_s = (w[:, None] * src).sum(axis=0) / total
        mu_d = (w[:, None] * dst).sum(axis=0) / total
        s, d = src - mu_s, dst - mu_d
        norm = (w * (s**2).sum(axis=1)).sum()
        a = (w * (s * d).sum(axis=1)).sum() / norm
        b = (w * (s[:, 0] * d[:, 1] - s[:, 1] * d[:, 0])).sum() / norm
        t = mu_d - np.array([a * mu_s[0] - b * mu_s[1], b * mu_s[0] + a * mu_s[1]])
        params = np.array([a, b, t[0], t[1]])
        if huber_px is not None:
            r = np.linalg.norm(apply_similarity(params, src) - dst, axis=1)
            w = base * np.minimum(1.0, huber_px / np.maximum(r, 1e-12))
    return params


def apply_similarity(params: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """``T(x)`` of eq. 8 for ``params (4,)`` = (a, b, tx, ty) and points ``xy (..., 2)`` px."""
    a, b, tx, ty = params
    return np.stack([a * xy[..., 0] - b * xy[..., 1] + tx, b * xy[..., 0] + a * xy[..., 1] + ty], axis=-1)


def invert_similarity(params: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """``T^-1(x')`` for ``params (4,)`` and points ``xy (..., 2)`` px."""
    a, b, tx, ty = params
    x, y = xy[..., 0] - tx, xy[..., 1] - ty
    scale = a * a + b * b
    return np.stack([(a * x + b * y) / scale, (-b * x + a * y) / scale], axis=-1)


def compensate(xy: np.ndarray, valid: np.ndarray, neutral: np.ndarray, rigid: np.ndarray, *,
               huber_px: float | None = None, min_points: int = 2) -> dict[str, np.ndarray]:
    """Per-frame similarity (eq. 8-9) from the rigid points, and compensated displacements.

    Parameters
    ----------
    xy : (T, N, 2) float
        Tracked points per frame, px.
    valid : (T, N) bool
        Their validity.
    neutral : (N, 2) float
        The neutral geometry ``x_i`` (e.g. the first frame), px.
    rigid : (R,) int
        Columns of the rigid points used to estimate ``T``.
    huber_px : float, optional
        Robust fit (see :func:`fit_similarity`).
    min_points : int
        Fewest valid rigid points for a frame's own fit; a frame with fewer is flagged invalid
        and its ``(a, b, tx, ty)`` linearly interpolated from the nearest valid frames (held at
        the ends).

    Returns
    -------
    dict
        ``params (T, 4)``, ``residual_px (T,)`` (RMS distance ``||T(x_i) - x'_i||`` over the
        rigid points used; NaN where not fitted), ``frame_valid (T,)``, ``d (T, N, 2)`` =
        ``T^-1(x'_i) - x_i`` px and ``d_valid (T, N)`` = point valid and frame valid.
    """
    n_frames = len(xy)
    params = np.full((n_frames, 4), np.nan)
    residual = np.full(n_frames, np.nan)
    fitted = np.zeros(n_frames, bool)
    for t in range(n_frames):
        use = rigid[valid[t, rigid]]
        if len(use) < max(min_points, 2):
            continue
        params[t] = fit_similarity(neutral[use], xy[t, use], huber_px=huber_px)
        residual[t] = np.sqrt(np.mean(np.sum((apply_similarity(params[t], neutral[use]) - xy[t, use]) ** 2, axis=1)))
        fitted[t] = True
    if not fitted.any():
        raise StageError(f"compensate: no frame has {max(min_points, 2)} valid rigid points")
    frames = np.arange(n_frames)
    for k in range(4):
        params[:, k] = np.interp(frames, frames[fitted], params[fitted, k])
    d = np.stack([invert_similarity(params[t], xy[t]) for t in range(n_frames)]) - neutral[None]
    return {"params": params, "residual_px": residual, "frame_valid": fitted, "d": d,
            "d_valid": valid & fitted[:, None]}


class SimilarityCompensate(SequenceStage):
    """``compensate.similarity``: head motion removed from tracked points (Sec. 12)."""

    name = "compensate.similarity"
    version = "1"
    doc = "2D similarity motion compensation from the rigid points (eq. 8-9), displacements T^-1(x')-x"
    inputs = {"points": "points", "neutral": "points"}
    optional_inputs = frozenset({"neutral"})
    outputs = {"similarity": "similarity", "displacements": "displacements"}
    params = (
        Param("layout", str, "zhang134", "layout name or YAML path (its rigid points)", file=True),
        Param("robust", bool, False, "Huber-reweighted least squares instead of plain least squares"),
        Param("huber_px", float, 1.0, "Huber threshold in px for the robust fit"),
        Param("min_points", int, 3, "fewest valid rigid points for a frame's own fit (else interpolated)"),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        params = {p.name: p.default for p in self.params} | dict(params)
        points = inputs["points"]
        names = np.asarray(points["names"])
        layout = load_layout(params["layout"])
        min_points = int(params["min_points"])
        rigid = rigid_columns(names, layout, at_least=max(min_points, 2), stage=self.name)
        neutral = points["xy"][0]
        if inputs.get("neutral") is not None:
            given = inputs["neutral"]
            columns = named_columns(np.asarray(given["names"]), tuple(str(n) for n in names))
            if len(columns) != len(names):
                raise StageError(f"{self.name}: the neutral input lacks some of the tracked points {list(names)}")
            neutral = np.asarray(given["xy"], dtype=np.float64)[0, columns]
        result = compensate(
            points["xy"], points["valid"], neutral, rigid,
            huber_px=float(params["huber_px"]) if params["robust"] else None,
            min_points=min_points,
        )
        return {
            "similarity": {"params": result["params"], "residual_px": result["residual_px"],
                           "valid": result["frame_valid"]},
            "displacements": {"d": result["d"], "valid": result["d_valid"], "names": names,
                              "neutral": neutral, **{k: points[k] for k in ("fps", "size") if k in points}},
        }
