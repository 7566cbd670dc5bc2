"""Runtime half of motion propagation: infer all feature point motions from a subset (Sec. 10.1).

The paper's algorithm, for an input set T of known point displacements::

    MotionPropagation
        V = 0
        while the stop criterion is not met:
            V(i) = v_i for each i in T                      # reset the known points
            hasBeenProcessed(F) = false for all sets F
            F = the set in the lowest hierarchy with F ∩ T ≠ ∅
            MotionPropagationFeaturePointSet(F)

    MotionPropagationFeaturePointSet(F*)
        if hasBeenProcessed(F*): return
        update V with Proj(V, F*)                         # project V(F*) into F*'s subspace
        hasBeenProcessed(F*) = true
        for each set F in hierarchy h-1 with F ∩ F* ≠ ∅: MotionPropagationFeaturePointSet(F)
        for each set F in hierarchy h+1 with F ∩ F* ≠ ∅: MotionPropagationFeaturePointSet(F)

Interpretation choices (stated in the README):

- "Lowest hierarchy" is the smallest level number (level 0 is the global set); ties between sets
  of one level go to the first in layout order.
- Proj(V, F) is the orthogonal projection onto the *affine* subspace ``mean_F + span(U_F)`` of
  the set's PCA (the mean displacement is part of the model, as PCA centres its data).
- The recursion visits the sets of a hierarchy in layout order. The order in which sets are
  updated within an iteration only depends on the starting set, so :func:`traversal_order` is
  computed once per starting set and the iteration runs on many frames at once (see
  :func:`motion_propagation` for the two ways frames are batched).
- Stop criterion: the mean over the input points of the distance between their values after
  this sweep and after the previous one (the first sweep compares with V = 0) falls below
  ``stop_progress_px``, or ``max_iterations`` sweeps were made.
- The returned displacements keep the input values at the input points (as the reset at the
  start of each iteration does); the other points carry the values of the last sweep. The
  reported input-point error is the mean distance between the last sweep's values at the input
  points and the inputs (the quantity of the paper's Fig. 12).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from stages.propagation.hierarchical_pca import HierarchicalPCA

_BLOCK = 16  # iterations of the basis run per block in the shared-mask batching
_READOUT_FRAMES = 2048  # frames per matrix product when reading a block out (bounds memory)


@dataclass(frozen=True)
class PropagationResult:
    """Output of :func:`motion_propagation` for T frames of N points.

    Attributes
    ----------
    displacements : (T, N, 2) float64
        Displacements of all points, px; input points keep their input values. Frames without
        any input point in a feature point set (without any input, for a layout whose sets
        cover every point) are all zero.
    iterations : (T,) int64
        Iterations (sweeps over the hierarchy) made per frame; 0 for frames without input.
    input_error_px : (T,) float64
        Mean distance, px, between the last sweep's values at the input points and the inputs;
        NaN for frames without input.
    error_history_px : (T, max_iterations) float64 or None
        The input-point error after each iteration (NaN after a frame stopped), when asked for.
    """

    displacements: np.ndarray
    iterations: np.ndarray
    input_error_px: np.ndarray
    error_history_px: np.ndarray | None


def start_sets(model: HierarchicalPCA, known: np.ndarray) -> np.ndarray:
    """The feature point set each frame's propagation starts from (Sec. 10.1).

    Parameters
    ----------
    model : HierarchicalPCA
    known : (T, N) bool
        True where a point's displacement is an input.

    Returns
    -------
    (T,) int64
        Index of the set in the lowest hierarchy (smallest level, then layout order) that
        contains an input point; -1 for frames whose input points lie in no set.
    """
    meets = np.stack([known[:, pts].any(axis=1) for pts in model.points], axis=1)
    by_level = np.lexsort((np.arange(model.n_sets), model.levels))
    ordered = meets[:, by_level]
    first = by_level[ordered.argmax(axis=1)]
    return np.where(ordered.any(axis=1), first, -1).astype(np.int64)


def traversal_order(model: HierarchicalPCA, start: int) -> tuple[int, ...]:
    """Sets in the order MotionPropagationFeaturePointSet(start) updates them (Sec. 10.1).

    Each set is updated when first reached (hasBeenProcessed), then the recursion goes to the
    overlapping sets of hierarchy h - 1, then of hierarchy h + 1. Sets that no chain of
    overlaps connects to ``start`` are not updated.
    """
    overlaps = model.overlaps()
    levels = model.levels
    processed = np.zeros(model.n_sets, dtype=bool)
    order: list[int] = []

    def visit(f: int) -> None:
        if processed[f]:
            return
        order.append(f)
        processed[f] = True
        for neighbour_level in (levels[f] - 1, levels[f] + 1):
            for g in np.flatnonzero((levels == neighbour_level) & overlaps[f]):
                visit(int(g))

    visit(int(start))
    return tuple(order)


def motion_propagation(
    model: HierarchicalPCA,
    displacements: np.ndarray,
    known: np.ndarray,
    *,
    stop_progress_px: float = 1e-3,
    max_iterations: int = 200,
    record_history: bool = False,
) -> PropagationResult:
    """MotionPropagation of Sec. 10.1 for a batch of frames.

    One iteration (reset the input points, then update V by Proj(V, F) for every set F in
    :func:`traversal_order`) is an affine map of V and of the inputs. Frames are batched in two
    ways, which give the same iterates up to rounding:

    - frames that share their input point set (a tracker's usual mask, a benchmark's 17 points)
      and are at least ``2 k + 1`` in number, for k input points: the iteration is run on the
      ``2 k + 1`` basis inputs (all zero, and each input coordinate set to 1), and every frame's
      iterates are the matching linear combination of theirs;
    - the other frames, grouped by starting set: the iteration is run on the frames themselves,
      each with its own reset mask.

    Parameters
    ----------
    model : HierarchicalPCA
        Expression subspaces of the feature point sets.
    displacements : (T, N, 2) float
        Input displacements from the neutral, px; only entries where ``known`` is True are read
        (the others may hold anything, NaN included).
    known : (T, N) bool
        The input point set T of each frame (a tracker's valid mask, a user's fixed points).
    stop_progress_px : float
        Stop a frame when the mean progress of its input points between two iterations is
        below this, px.
    max_iterations : int
        Iteration cap.
    record_history : bool
        Keep the input-point error of every iteration (for the convergence plot, Fig. 12).

    Returns
    -------
    PropagationResult
    """
    displacements = np.asarray(displacements, dtype=np.float64)
    known = np.asarray(known, dtype=bool)
    n_points = model.n_points
    if displacements.ndim != 3 or displacements.shape[1:] != (n_points, 2):
        raise ValueError(f"displacements must be (T, {n_points}, 2), got {displacements.shape}")
    if known.shape != displacements.shape[:2]:
        raise ValueError(f"mask must be {displacements.shape[:2]}, got {known.shape}")
    if max_iterations < 1 or not stop_progress_px >= 0:
        raise ValueError("max_iterations must be >= 1 and stop_progress_px >= 0")
    inputs = np.where(known[..., None], displacements, 0.0)
    if not np.isfinite(inputs).all():
        raise ValueError("input displacements contain NaN or infinite values at valid points")

    n_frames = known.shape[0]
    result = PropagationResult(
        displacements=np.zeros((n_frames, n_points, 2)),
        iterations=np.zeros(n_frames, dtype=np.int64),
        input_error_px=np.full(n_frames, np.nan),
        error_history_px=np.full((n_frames, max_iterations), np.nan) if record_history else None,
    )
    options = {"stop_progress_px": stop_progress_px, "max_iterations": max_iterations}
    sweep = Sweep(model)
    starts = start_sets(model, known)
    packed = np.ascontiguousarray(np.packbits(known, axis=1))
    _, first_frame, pattern_of_frame, counts = np.unique(
        packed.view(np.dtype((np.void, packed.shape[1]))).reshape(-1),
        return_index=True,
        return_inverse=True,
        return_counts=True,
    )
    shared = np.zeros(n_frames, dtype=bool)
    for p, (frame, count) in enumerate(zip(first_frame, counts)):
        pattern = known[frame]
        if starts[frame] >= 0 and count >= 2 * pattern.sum() + 1:
            frames = np.flatnonzero(pattern_of_frame == p)
            propagate_shared_mask(sweep, starts[frame], inputs[frames], pattern, frames, result, **options)
            shared[frames] = True
    for start in np.unique(starts[(starts >= 0) & ~shared]):
        frames = np.flatnonzero((starts == start) & ~shared)
        _propagate_frames(sweep, start, inputs[frames], known[frames], frames, result, **options)
    return result


class Sweep:
    """One iteration's updates, V <- Proj(V, F) for F in the traversal order (Sec. 10.1).

    V is held as ``(2N, C)``: one column per frame (or per basis input), rows x0, y0, x1, y1,
    ... so that a set's rows are gathered as whole contiguous rows.
    """

    def __init__(self, model: HierarchicalPCA) -> None:
        self.model = model
        self.rows = [np.stack([2 * p, 2 * p + 1], axis=1).reshape(-1) for p in model.points]
        self.means = [m[:, None] for m in model.means]
        self._orders: dict[int, tuple[int, ...]] = {}

    def __call__(self, v: np.ndarray, start: int) -> None:
        """Update ``v`` (2N, C) in place by one pass of MotionPropagationFeaturePointSet(start)."""
        if start not in self._orders:
            self._orders[start] = traversal_order(self.model, start)
        for s in self._orders[start]:
            u, rows, mean = self.model.components[s], self.rows[s], self.means[s]
            x = v[rows] - mean
            v[rows] = u @ (u.T @ x) + mean


def _propagate_frames(
    sweep: Sweep,
    start: int,
    inputs: np.ndarray,
    known: np.ndarray,
    frames: np.ndarray,
    result: PropagationResult,
    *,
    stop_progress_px: float,
    max_iterations: int,
) -> None:
    """Iterate on the frames themselves (each with its own mask); write into ``result``.

    A frame leaves the batch when it meets the stop criterion; the others go on unchanged.
    """
    n_batch, n_points = known.shape
    v_in = np.ascontiguousarray(inputs.reshape(n_batch, 2 * n_points).T)  # (2N, B)
    known_pts = np.ascontiguousarray(known.T)  # (N, B)
    known_rows = np.repeat(known_pts, 2, axis=0)  # (2N, B)
    v = np.zeros_like(v_in)
    v_prev = np.zeros_like(v_in)
    left = frames.copy()
    for iteration in range(1, max_iterations + 1):
        np.copyto(v, v_in, where=known_rows)
        sweep(v, start)
        error = _mean_input_distance(v - v_in, known_pts)
        progress = _mean_input_distance(v - v_prev, known_pts)
        if result.error_history_px is not None:
            result.error_history_px[left, iteration - 1] = error
        stop = (progress < stop_progress_px) | (iteration == max_iterations)
        if stop.any():
            result.iterations[left[stop]] = iteration
            result.input_error_px[left[stop]] = error[stop]
            finished = np.where(known_rows[:, stop], v_in[:, stop], v[:, stop])
            result.displacements[left[stop]] = finished.T.reshape(-1, n_points, 2)
            go_on = ~stop
            if not go_on.any():
                return
            left, v, v_in = left[go_on], v[:, go_on], v_in[:, go_on]
            known_pts, known_rows = known_pts[:, go_on], known_rows[:, go_on]
        v_prev = v.copy()


def propagate_shared_mask(
    sweep: Sweep,
    start: int,
    inputs: np.ndarray,
    known: np.ndarray,
    frames: np.ndarray,
    result: PropagationResult,
    *,
    stop_progress_px: float,
    max_iterations: int,
) -> None:
    """Iterate on the basis inputs of one shared mask ``known`` (N,); frames are their combinations.

    Basis column 0 has all inputs 0, column j > 0 has input coordinate j set to 1 (x of the k
    input points, then their y). The iteration is affine in the inputs, so a frame with input
    coordinates ``x`` (2k,) has the iterates ``V @ w``, weights ``w = (1 - sum(x), x)``. The
    basis is iterated ``_BLOCK`` iterations at a time and the frames' progress over the block is
    read with one matrix product.
    """
    n_batch, n_points = inputs.shape[:2]
    points = np.flatnonzero(known)
    known_rows = np.concatenate([2 * points, 2 * points + 1])  # (2k,): x of the k points, then y
    n_inputs = known_rows.size
    basis_in = np.concatenate([np.zeros((n_inputs, 1)), np.eye(n_inputs)], axis=1)  # (2k, 2k + 1)
    x = inputs.reshape(n_batch, 2 * n_points)[:, known_rows]  # (B, 2k)
    weights = np.concatenate([1.0 - x.sum(axis=1, keepdims=True), x], axis=1)  # (B, 2k + 1)
    v = np.zeros((2 * n_points, n_inputs + 1))
    y_last = np.zeros((n_inputs, n_inputs + 1))
    left = frames.copy()
    for first in range(1, max_iterations + 1, _BLOCK):
        n_block = min(_BLOCK, max_iterations + 1 - first)
        iterates = np.empty((n_block,) + v.shape)  # (L, 2N, 2k + 1)
        for j in range(n_block):
            v[known_rows] = basis_in
            sweep(v, start)
            iterates[j] = v
        y = iterates[:, known_rows]  # (L, 2k, 2k + 1): the input points after each sweep
        progress = _combined_distance(weights, np.diff(y, axis=0, prepend=y_last[None]))
        y_last = y[-1]
        stop = progress < stop_progress_px  # (b, L)
        if first + n_block > max_iterations:
            stop[:, -1] = True
        stops = stop.any(axis=1)
        stop_at = np.where(stops, stop.argmax(axis=1), n_block - 1)
        if result.error_history_px is not None:
            error = _combined_distance(weights, y, minus=x)
            error[np.arange(n_block)[None] > stop_at[:, None]] = np.nan
            result.error_history_px[left, first - 1 : first - 1 + n_block] = error
        for j in np.unique(stop_at[stops]):
            done = stops & (stop_at == j)
            finished = weights[done] @ iterates[j].T  # (b, 2N)
            result.iterations[left[done]] = first + j
            result.input_error_px[left[done]] = _mean_point_distance(finished[:, known_rows] - x[done])
            finished[:, known_rows] = x[done]
            result.displacements[left[done]] = finished.reshape(-1, n_points, 2)
        if stops.all():
            return
        left, weights, x = left[~stops], weights[~stops], x[~stops]


def _combined_distance(weights: np.ndarray, stack: np.ndarray, *, minus: np.ndarray | None = None) -> np.ndarray:
    """(B, L) mean point distance of each frame's combination of the basis values ``stack``.

    ``stack`` (L, 2k, C) holds, per iteration, the 2k input coordinates of the C basis columns;
    frame b's values are ``stack[l] @ weights[b]`` (minus ``minus[b]`` (2k,) when given).
    """
    n_block, n_coords, n_basis = stack.shape
    columns = stack.transpose(2, 0, 1).reshape(n_basis, n_block * n_coords)  # (C, L * 2k)
    out = np.empty((len(weights), n_block))
    for lo in range(0, len(weights), _READOUT_FRAMES):
        values = (weights[lo : lo + _READOUT_FRAMES] @ columns).reshape(-1, n_block, n_coords)
        if minus is not None:
            values -= minus[lo : lo + _READOUT_FRAMES, None]
        out[lo : lo + _READOUT_FRAMES] = _mean_point_distance(values)
    return out


def _mean_point_distance(diff: np.ndarray) -> np.ndarray:
    """(...,) mean over k points of the length of point differences (..., 2k): k x, then k y."""
    k = diff.shape[-1] // 2
    return np.sqrt(diff[..., :k] ** 2 + diff[..., k:] ** 2).mean(axis=-1)


def _mean_input_distance(diff: np.ndarray, known_pts: np.ndarray) -> np.ndarray:
    """(B,) mean over each frame's input points (``known_pts`` (N, B)) of the length of the point
    differences ``diff`` (2N, B), rows x0, y0, x1, y1, ..."""
    dist = np.sqrt((diff.reshape(known_pts.shape[0], 2, -1) ** 2).sum(axis=1))
    return np.where(known_pts, dist, 0.0).sum(axis=0) / known_pts.sum(axis=0)


def propagate_edit(
    model: HierarchicalPCA,
    current_points: np.ndarray,
    fixed: Mapping[int, np.ndarray] | np.ndarray,
    *,
    stop_progress_px: float = 1e-3,
    max_iterations: int = 200,
) -> np.ndarray:
    """The most likely full geometry given the points a user fixed or dragged (Sec. 13).

    Parameters
    ----------
    model : HierarchicalPCA
    current_points : (N, 2) float
        The geometry being edited, px, in the neutral's frame.
    fixed : dict {point index: (x, y)} or (N,) bool
        Either the dragged/fixed points with their new positions, px, or a mask of the points of
        ``current_points`` to hold where they are.
    stop_progress_px, max_iterations
        As in :func:`motion_propagation`.

    Returns
    -------
    (N, 2) float64
        Fixed points where they were put, every other point moved to its inferred position
        (dragging the nose tip moves the whole nose region). With no fixed point, the neutral.
    """
    current = np.asarray(current_points, dtype=np.float64)
    if current.shape != model.neutral.shape:
        raise ValueError(f"current_points must be {model.neutral.shape}, got {current.shape}")
    target = current.copy()
    if isinstance(fixed, Mapping):
        mask = np.zeros(model.n_points, dtype=bool)
        for index, xy in fixed.items():
            if not 0 <= int(index) < model.n_points:
                raise ValueError(f"fixed point index {index} is outside 0..{model.n_points - 1}")
            mask[int(index)] = True
            target[int(index)] = np.asarray(xy, dtype=np.float64)
    else:
        mask = np.asarray(fixed, dtype=bool)
        if mask.shape != (model.n_points,):
            raise ValueError(f"fixed mask must be ({model.n_points},), got {mask.shape}")
    propagated = motion_propagation(
        model,
        (target - model.neutral)[None],
        mask[None],
        stop_progress_px=stop_progress_px,
        max_iterations=max_iterations,
    )
    return model.neutral + propagated.displacements[0]
