"""Expression mapping's geometric step (paper Sec. 11, 14.1): the performer's motion-compensated
displacement vectors carried onto the target's neutral geometry.

Traditional expression mapping adds the performer's displacement ``d_i = T^-1(x'_i) - x_i``
(Sec. 12) to the target's neutral point ``y_i``. Faces differ in size and the two neutrals in
in-plane orientation, so the displacements are first brought into the target's frame by the
linear part ``S`` of a normalization: the target geometry is ``y_i + S_i d_i``.

``mode``:

- ``similarity`` (default): ``S = [[a, -b], [b, a]]`` of the least-squares similarity (eq. 8-9)
  mapping the performer's neutral rigid points onto the target's: the face-size ratio and the
  in-plane rotation between the two neutrals.
- ``region``: the rotation of ``similarity`` with a scale per feature point set of the layout's
  hierarchy level 1 (Sec. 10): the RMS radius about their centroid of the set's points on the
  target's neutral over the same on the performer's. A point in several sets takes the mean of
  their scales; a point in none, or a set with fewer than 3 tracked points, the global scale.
- ``none``: ``S = I``, displacements in px as they are.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from runner.stage import Context, Param, SequenceStage, StageError
from stages.actor_pack import load_pack
from stages.geometry.compensate import fit_similarity
from stages.geometry.subset import named_columns, rigid_columns

MODES = ("similarity", "region", "none")


def rms_radius(xy: np.ndarray) -> float:
    """RMS distance ``(n, 2) -> float`` of points from their centroid, px."""
    return float(np.sqrt(np.mean(np.sum((xy - xy.mean(axis=0)) ** 2, axis=1))))


def displacement_transforms(performer: np.ndarray, target: np.ndarray, rigid: np.ndarray, *,
                            mode: str = "similarity", regions: Sequence[np.ndarray] = ()) -> np.ndarray:
    """The linear maps ``S_i (N, 2, 2)`` applied to each point's displacement.

    Parameters
    ----------
    performer, target : (N, 2) float
        The performer's and the target's neutral geometry of the same N points, px.
    rigid : (R,) int
        Columns of the rigid points (the global fit).
    mode : str
        ``similarity``, ``region`` or ``none`` (module docstring).
    regions : sequence of (K,) int arrays
        Columns of each region (``region`` mode).
    """
    n = len(performer)
    if mode == "none":
        return np.broadcast_to(np.eye(2), (n, 2, 2)).copy()
    if mode not in MODES:
        raise ValueError(f"unknown mapping mode {mode!r}; expected one of {MODES}")
    a, b, _, _ = fit_similarity(performer[rigid], target[rigid])
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


class ExpressionMap(SequenceStage):
    """``map.expression``: performer displacements -> target geometry of the tracked subset.

    The output covers the whole layout of the target's pack, as motion propagation (Sec. 10)
    expects: ``xy (T, N, 2)`` with the mapped tracked points valid and every other point at the
    target's neutral position, flagged invalid (propagation infers it).
    """

    name = "map.expression"
    version = "1"
    doc = "carry compensated performer displacements onto the target's neutral (Sec. 11), size-normalized"
    inputs = {"displacements": "displacements", "pack": "dir"}
    outputs = {"points": "points"}
    params = (Param("mode", str, "similarity", "displacement normalization (similarity | region | none)",
                    choices=MODES),)

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        params = {p.name: p.default for p in self.params} | dict(params)
        bundle = inputs["displacements"]
        if "neutral" not in bundle:
            raise StageError(f"{self.name}: the displacements carry no 'neutral' (the performer's neutral geometry)")
        pack = load_pack(inputs["pack"])
        layout = pack.layout
        names = np.asarray(bundle["names"])
        try:
            rows = [layout.index(str(n)) for n in names]
        except (KeyError, ValueError) as exc:
            raise StageError(f"{self.name}: point {exc} is not in the pack's layout {layout.name}") from None
        rigid = rigid_columns(names, layout, at_least=2, stage=self.name)
        regions = [
            named_columns(names, tuple(layout.point_names[i] for i in fps.points))
            for fps in layout.feature_point_sets if fps.level == 1
        ]
        target = np.asarray(pack.neutral.points, dtype=np.float64)[rows]
        transforms = displacement_transforms(np.asarray(bundle["neutral"], dtype=np.float64), target, rigid,
                                             mode=params["mode"], regions=regions)
        mapped = map_expression(np.asarray(bundle["d"], dtype=np.float64), target, transforms)
        n_frames = len(mapped)
        xy = np.repeat(np.asarray(pack.neutral.points, dtype=np.float64)[None], n_frames, axis=0)
        xy[:, rows] = mapped
        valid = np.zeros((n_frames, layout.n_points), bool)
        valid[:, rows] = np.asarray(bundle["valid"], bool)
        out = {"xy": xy, "valid": valid, "names": np.array(layout.point_names)}
        out.update({k: np.asarray(bundle[k]) for k in ("fps", "size") if k in bundle})
        return {"points": out}
