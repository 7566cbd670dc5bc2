"""Per-subregion convex-combination coefficients for target geometries (Sec. 6, 8; eq. 2-5).

:class:`SubregionQP` gathers, for every subregion of a synthesis model, its feature points G^R
from the example geometries (face subregions) or the teeth example geometries (the teeth
subregion, Sec. 8) once, and solves the QPs of a batch of frames in one call of
:func:`stages.synthesis.qp.project_onto_convex_hull` per family. The ``synthesis.coefficients``
stage publishes the coefficients ``synthesize`` used with their subregion and example names (port
type ``coefficients``, the format ``write.data`` reads).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from runner.stage import Context, SequenceStage, StageError
from stages.synthesis.bundles import COEFFICIENTS, SYNTHESIS_COEFFS, SYNTHESIS_MODEL
from stages.synthesis.qp import project_onto_convex_hull

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only; imported where used, so that importing this module stays light
    import torch

__all__ = ["SubregionQP", "target_geometry", "candidate_table", "NameCoefficients"]

QP_MODES = ("full", "global")


@dataclass
class _Family:
    """Padded gather indices of one family of QPs (face subregions or teeth)."""

    rows: list[int]  # the subregions (coefficient rows) they fill
    index: torch.Tensor  # (R, n) point indices, padded with 0
    weight: torch.Tensor  # (R, 2 n) 1 for real coordinates, 0 for padding
    examples: torch.Tensor  # (R, M, 2 n) example coordinates, zero on padding


class SubregionQP:
    """The QPs of eq. 2-5 of one synthesis model, batched over frames and subregions.

    Parameters
    ----------
    model : dict of arrays
        A ``synthesis_model`` bundle (keys ``subregion_points``, ``subregion_teeth``,
        ``example_points``, ``teeth_points``).
    device : str
    ridge_px : float
        Coefficient regularisation ``tau``, px: every QP (per subregion, global and teeth) gets
        the Tikhonov term ``n_R tau^2 ||c||^2`` (``n_R`` its number of points), i.e. per point the
        objective is the mean squared point distance plus ``tau^2 ||c||^2``: spreading the
        combination from one example over many is worth up to ``tau^2`` of mean squared point
        distance. 0 is the plain eq. 2 (see docs/synthesis.md, "Per-subregion vs global on real
        faces", for the measurements behind the default).
    """

    def __init__(self, model: Mapping[str, np.ndarray], *, device: str = "cpu", ridge_px: float = 0.0) -> None:
        if not ridge_px >= 0:
            raise ValueError(f"ridge_px must be >= 0, got {ridge_px}")
        self.device = device
        self.ridge_px = float(ridge_px)
        member = np.asarray(model["subregion_points"], bool)
        teeth = np.asarray(model["subregion_teeth"], bool)
        self.n_subregions = len(member)
        self.K = max(len(model["example_points"]), len(model["teeth_points"]), 1)
        face_rows = [s for s in range(len(member)) if not teeth[s]]
        teeth_rows = [s for s in range(len(member)) if teeth[s]]
        self.face = self._family(face_rows, [member[s] for s in face_rows], model["example_points"])
        self.global_ = self._family(face_rows, [member[face_rows].any(0)], model["example_points"])
        self.teeth = self._family(teeth_rows, [member[s] for s in teeth_rows], model["teeth_points"])

    def _family(self, rows: list[int], members: list[np.ndarray], example_points: np.ndarray) -> _Family:
        """Gather G^R of each subregion (``members``: (N,) bool each), zero-padded to a common size."""
        import torch

        n = max((int(m.sum()) for m in members), default=1)
        index = np.zeros((len(members), n), np.int64)
        weight = np.zeros((len(members), n, 2))
        for k, m in enumerate(members):
            idx = np.flatnonzero(m)
            index[k, : len(idx)] = idx
            weight[k, : len(idx)] = 1.0
        ex = np.asarray(example_points, np.float64)[:, index] * weight[None]  # (M, R, n, 2)
        return _Family(
            rows,
            torch.from_numpy(index).to(self.device),
            torch.from_numpy(weight.reshape(len(members), -1)).to(self.device),
            torch.from_numpy(ex.reshape(len(ex), len(members), -1).transpose(1, 0, 2).copy()).to(self.device),
        )

    def _solve(self, family: _Family, points: torch.Tensor, coeffs: torch.Tensor, dist: torch.Tensor) -> None:
        if not family.rows or family.examples.shape[1] == 0:
            return
        B, R = len(points), family.index.shape[0]
        target = points[:, family.index].reshape(B, R, -1) * family.weight
        ridge = self.ridge_px**2 * family.weight.sum(-1) / 2  # tau^2 n_R per subregion
        c, d2 = project_onto_convex_hull(
            family.examples[None].expand(B, -1, -1, -1).reshape(B * R, *family.examples.shape[1:]),
            target.reshape(B * R, -1),
            weights=family.weight[None].expand(B, -1, -1).reshape(B * R, -1),
            ridge=ridge[None].expand(B, -1).reshape(B * R),
        )
        c, d2 = c.view(B, R, -1), d2.view(B, R)
        rows = family.rows
        coeffs[:, rows, : c.shape[-1]] = c.expand(B, len(rows), -1)  # R = 1 in global mode: one for all
        dist[:, rows] = d2.expand(B, len(rows))

    def coefficients(self, points: np.ndarray, *, mode: str = "full") -> tuple[torch.Tensor, torch.Tensor]:
        """Per-frame, per-subregion convex-combination coefficients (eq. 2-5).

        Parameters
        ----------
        points : (B, N, 2) float, px, the target geometry per frame
        mode : ``"full"`` (per subregion) or ``"global"`` (one combination over the union of the
            face subregions' points, used for every face subregion: Pighin et al.)

        Returns
        -------
        coeffs : (B, S, K) float64; face subregions over the ``M`` examples, the teeth subregion over
            the ``Mt`` teeth examples, zero-padded to ``K = max(M, Mt)``.
        distance2 : (B, S) float64, the squared distance of each combination to the target's
            points (eq. 5; the distance to the hull when ``ridge_px`` is 0), px^2.
        """
        import torch

        if mode not in QP_MODES:
            raise ValueError(f"mode must be one of {QP_MODES}, got {mode!r}")
        pts = torch.as_tensor(np.asarray(points, np.float64), device=self.device)
        B = len(pts)
        coeffs = torch.zeros(B, self.n_subregions, self.K, dtype=torch.float64, device=self.device)
        dist = torch.zeros(B, self.n_subregions, dtype=torch.float64, device=self.device)
        self._solve(self.global_ if mode == "global" else self.face, pts, coeffs, dist)
        self._solve(self.teeth, pts, coeffs, dist)
        return coeffs, dist


def target_geometry(inputs: Mapping[str, Any], *, stage: str) -> tuple[np.ndarray, Mapping[str, np.ndarray]]:
    """The target's points per frame from a ``points`` or a ``displacements`` input.

    ``points``: ``xy (T, N, 2)``; ``displacements``: ``d (T, N, 2)`` added to the model's
    neutral points. Returns ``(xy (T, N, 2) float64, the bundle used)``.

    Raises
    ------
    StageError
        Neither is connected, or the point count differs from the synthesis model's layout.
    """
    model = inputs["model"]
    if inputs.get("points") is not None:
        bundle = inputs["points"]
        xy = np.asarray(bundle["xy"], np.float64)
    elif inputs.get("displacements") is not None:
        bundle = inputs["displacements"]
        xy = np.asarray(model["neutral_points"], np.float64) + np.asarray(bundle["d"], np.float64)
    else:
        raise StageError(f"{stage}: connect a 'points' or a 'displacements' input")
    n = len(model["standard_points"])
    if xy.ndim != 3 or xy.shape[1:] != (n, 2):
        raise StageError(f"{stage}: input geometry has shape {xy.shape}, the synthesis model needs (T, {n}, 2)")
    return xy, bundle


def candidate_table(coeffs: np.ndarray, model: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Coefficients laid out over all examples by name: the ``coefficients`` bundle of ``write.data``.

    Parameters
    ----------
    coeffs : (T, S, K) as returned by :meth:`SubregionQP.coefficients`

    Returns
    -------
    ``coeff (T, S, M + Mt)`` (examples then teeth examples; NaN where an example is not a
    candidate of the subregion), ``subregions (S,)``, ``examples (M + Mt,)``.
    """
    M, Mt = len(model["example_points"]), len(model["teeth_points"])
    teeth = np.asarray(model["subregion_teeth"], bool)
    table = np.full(coeffs.shape[:2] + (M + Mt,), np.nan)
    table[:, ~teeth, :M] = coeffs[:, ~teeth, :M]
    table[:, teeth, M:] = coeffs[:, teeth, :Mt]
    names = np.concatenate([np.asarray(model["example_names"], str), np.asarray(model["teeth_names"], str)])
    return {"coeff": table, "subregions": np.asarray(model["subregion_names"], str), "examples": names}


class NameCoefficients(SequenceStage):
    """``synthesis.coefficients``: the coefficients ``synthesize`` used, laid out by name.

    A frame stage's bundle outputs are joined chunk by chunk along their first axis, so
    ``synthesize`` cannot publish the subregion and example names itself; this stage adds them
    (:func:`candidate_table`) to exactly the coefficients the frames were composited with (zero in
    ``warp-only`` mode), for ``write.data``.
    """

    name = "synthesis.coefficients"
    version = "2"
    doc = "the coefficients synthesize composited with (eq. 2-5), laid out with subregion/example names"
    inputs = {"model": SYNTHESIS_MODEL, "coeffs": SYNTHESIS_COEFFS}
    outputs = {"coefficients": COEFFICIENTS}

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        model = inputs["model"]
        coeffs = np.asarray(inputs["coeffs"]["coeffs"], np.float64)
        expected = (len(model["subregion_names"]), max(len(model["example_points"]), len(model["teeth_points"]), 1))
        if coeffs.ndim != 3 or coeffs.shape[1:] != expected:
            raise StageError(
                f"{self.name}: input 'coeffs' has shape {coeffs.shape}, the model needs (T, {expected[0]}, {expected[1]})"
            )
        return {"coefficients": candidate_table(coeffs, model)}
