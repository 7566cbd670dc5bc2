"""Motion compensation with a 2D similarity model (paper Sec. 12, eq. 8-9).

Per frame, the similarity ``T(a, b, tx, ty)`` of eq. 8,

    T(x, y) = [[a, -b], [b, a]] @ (x, y) + (tx, ty),

that best maps the neutral face's rigid points ``x_i`` onto the frame's ``x'_i`` in the least
squares sense of eq. 9, ``min sum_i ||T(x_i) - x'_i||^2``, has a closed form
(:mod:`stages.geometry.similarity`). The head motion is then undone and the displacement
``T^-1(x'_i) - x_i`` of every tracked point is what feeds expression mapping (Sec. 12).
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from runner.stage import Context, Param, SequenceStage, StageError
from stages.geometry.bundles import DISPLACEMENTS, POINTS, SIMILARITY
from stages.geometry.similarity import apply_similarity, fit_similarity, invert_similarity
from stages.geometry.subset import named_columns, rigid_columns
from stages.layout import load_layout


def compensate(
    xy: np.ndarray,
    valid: np.ndarray,
    neutral: np.ndarray,
    rigid: np.ndarray,
    *,
    huber_px: float | None = None,
    min_points: int = 2,
) -> dict[str, np.ndarray]:
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
    return {"params": params, "residual_px": residual, "frame_valid": fitted, "d": d, "d_valid": valid & fitted[:, None]}


class SimilarityCompensate(SequenceStage):
    """``compensate.similarity``: head motion removed from tracked points (Sec. 12)."""

    name = "compensate.similarity"
    version = "1"
    doc = "2D similarity motion compensation from the rigid points (eq. 8-9), displacements T^-1(x')-x"
    inputs = {"points": POINTS, "neutral": POINTS}
    optional_inputs = frozenset({"neutral"})
    outputs = {"similarity": SIMILARITY, "displacements": DISPLACEMENTS}
    params = (
        Param("layout", str, "zhang134", "layout name or YAML path (its rigid points)", file=True),
        Param("robust", bool, False, "Huber-reweighted least squares instead of plain least squares"),
        Param("huber_px", float, 1.0, "Huber threshold in px for the robust fit", min=0.01, max=1000.0),
        Param("min_points", int, 3, "fewest valid rigid points for a frame's own fit (else interpolated)", min=2, max=1000),
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
            points["xy"],
            points["valid"],
            neutral,
            rigid,
            huber_px=float(params["huber_px"]) if params["robust"] else None,
            min_points=min_points,
        )
        return {
            "similarity": {"params": result["params"], "residual_px": result["residual_px"], "valid": result["frame_valid"]},
            "displacements": {
                "d": result["d"],
                "valid": result["d_valid"],
                "names": names,
                "neutral": neutral,
                **{k: points[k] for k in ("fps", "size") if k in points},
            },
        }
