"""Motion propagation (Sec. 10.1) of many positions of one pinned set: its sweeps recorded once.

While a point is dragged in the editor (Sec. 13) the pinned set does not change, only the
pinned positions. One
iteration of MotionPropagation (reset the input points, then ``V <- Proj(V, F)`` for every set
``F`` of the traversal order) is affine in the inputs, so the library's shared-mask batching
(:func:`stages.propagation.propagate.motion_propagation`, for frames that share their input
points) iterates the ``2k + 1`` *basis inputs* of a set of ``k`` input points (all zero, and
each input coordinate set to 1) and reads every frame's iterates, and its data-dependent stop
(mean progress of the input points below ``stop_progress_px``), as linear combinations of
theirs. The basis iterates depend on the pinned set alone: :class:`PinnedPropagation` records
them the first time a set is propagated and replays them for every later position of the same
set, so an update of a drag costs the readout only (1.8 against 17 ms of CPU on the 600x800
demo target). The result is the library's shared-mask result (the same sweeps, the same
readout), which equals :func:`stages.propagation.propagate.propagate_edit` up to rounding
(1e-12 px there).
"""

from __future__ import annotations

import inspect
import threading
from typing import Mapping

import numpy as np

from stages.propagation.hierarchical_pca import HierarchicalPCA
from stages.propagation.propagate import PropagationResult, Sweep, propagate_edit, propagate_shared_mask, start_sets

__all__ = ["PinnedPropagation"]

_DEFAULTS = inspect.signature(propagate_edit).parameters  # the pipeline's stop and iteration cap
MAX_RECORDED_PINS = 16  # more pinned points: the 2k + 1 basis columns cost more than one frame's sweeps


class _Recorder:
    """A sweep (``sweep(v, start)``, in place) that records its outputs, then replays them."""

    def __init__(self, sweep: Sweep) -> None:
        self.sweep = sweep
        self.outputs: list[np.ndarray] = []
        self.calls = 0

    def __call__(self, v: np.ndarray, start: int) -> None:
        if self.calls < len(self.outputs):
            v[...] = self.outputs[self.calls]
        else:
            self.sweep(v, start)
            self.outputs.append(v.copy())
        self.calls += 1


class PinnedPropagation:
    """:func:`~stages.propagation.propagate.propagate_edit` (same signature and defaults) with the
    basis sweeps of the latest pinned set recorded (module docstring).

    Parameters
    ----------
    model : HierarchicalPCA
        The target's hierarchical PCA; calls must pass this model.

    Sets of more than ``MAX_RECORDED_PINS`` points, and sets whose points lie in no feature
    point set, go to ``propagate_edit`` itself. Calls are serialised (renderer threads share
    one instance).
    """

    def __init__(self, model: HierarchicalPCA) -> None:
        self.model = model
        self.sweep = Sweep(model)
        self.recorded: tuple[bytes, _Recorder] | None = None  # (pinned mask, its sweeps)
        self.lock = threading.Lock()

    def __call__(
        self,
        model: HierarchicalPCA,
        current_points: np.ndarray,
        fixed: Mapping[int, np.ndarray],
        *,
        stop_progress_px: float = _DEFAULTS["stop_progress_px"].default,
        max_iterations: int = _DEFAULTS["max_iterations"].default,
    ) -> np.ndarray:
        """The most likely geometry given the pinned points ``fixed`` ({index: (x, y) px}),
        starting from ``current_points (N, 2)`` px, as ``propagate_edit``.

        Returns
        -------
        (N, 2) float64, px: pinned points where they were put, the others propagated.

        Raises
        ------
        ValueError
            ``model`` is not this instance's, or as ``propagate_edit`` (shape, index range).
        """
        if model is not self.model:
            raise ValueError("PinnedPropagation was made for another HierarchicalPCA model")
        current = np.asarray(current_points, dtype=np.float64)
        indices = [int(i) for i in fixed]
        known = np.zeros(model.n_points, dtype=bool)
        if 0 < len(indices) <= MAX_RECORDED_PINS and all(0 <= i < model.n_points for i in indices):
            known[indices] = True
        start = int(start_sets(model, known[None])[0])
        target = current.copy()
        if start >= 0 and current.shape == model.neutral.shape:
            for index, xy in fixed.items():
                target[int(index)] = np.asarray(xy, dtype=np.float64)
        if start < 0 or current.shape != model.neutral.shape or not np.isfinite(target[known]).all():
            # no input point in a set, too many pins, or input that propagate_edit refuses
            return propagate_edit(model, current, fixed, stop_progress_px=stop_progress_px, max_iterations=max_iterations)
        result = PropagationResult(np.zeros((1, model.n_points, 2)), np.zeros(1, np.int64), np.full(1, np.nan), None)
        with self.lock:
            key = known.tobytes()
            if self.recorded is None or self.recorded[0] != key:
                self.recorded = (key, _Recorder(self.sweep))
            recorder = self.recorded[1]
            recorder.calls = 0
            propagate_shared_mask(
                recorder,
                start,
                (target - model.neutral)[None],
                known,
                np.zeros(1, np.int64),
                result,
                stop_progress_px=stop_progress_px,
                max_iterations=max_iterations,
            )
        return model.neutral + result.displacements[0]
