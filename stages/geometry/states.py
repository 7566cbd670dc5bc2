"""Expression states of a face geometry: eyes shut, squinted or wide (each eye), lips sealed or
pressed, pucker and "O", brow furrow and raise, smile, jaw open.

A viewer judges a performance by states more than by motion: whether the eyes shut when the
performer's do, whether the lips close on a "p", whether a frown appears. Each state is read from
one *state signal* of the zhang134 layout's points, in the face's own eye-line frame
(:func:`stages.geometry.signals.eye_line_frame`: eye distance ``e``, unit normal ``n`` down the
face), so head roll and face size cancel out:

==================  ======================================================================
signal              definition (``e``: outer-eye-corner distance; ``n``: down the face)
==================  ======================================================================
``eye_open_l/_r``   lid gap: mean over the facing lid pairs (``eye_*_2``/``_10``,
                    ``_3``/``_9``, ``_4``/``_8``) of (lower - upper) . n, over ``e``
``mouth_open``      inner-lip gap (:mod:`stages.geometry.signals`), over ``e``
``mouth_width``     outer mouth corners' distance, over ``e``
``lip_thickness``   red-lip height at the middle (``mouth_outer_4`` to ``mouth_outer_12``
                    along n) minus the inner gap there, over ``e``
``smile``           mouth corners' height above the mouth's middle (``mouth_outer_4``,
                    ``mouth_outer_12``), along -n, over ``e``
``brow_raise``      brows' mean height above the eye line, over ``e``
``brow_furrow``     distance between the inner brow ends (mean of ``brow_*_0`` and
                    ``brow_*_7`` of each brow), over ``e``
==================  ======================================================================

A state is a signal compared with the same face's neutral (:data:`STATES`): eyes by the ratio of
the lid gap to the neutral's (0 shut, 1 as in the neutral), the mouth's opening as it is (a
closed mouth is a gap near 0 on any face), the rest as a change from the neutral in eye distances
or as a ratio. The same table decides what a pack covers (the range of each state over its
example expressions, ``pack.yaml``'s ``coverage``), what a performance demands, and which frames
the run report lists.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from stages.geometry.signals import MOUTH_CORNERS, eye_line_frame, expression_signals, named_points

EYE_PAIRS = ((2, 10), (3, 9), (4, 8))  # (upper, lower) lid points facing each other, per eye
INNER_LIP_MIDDLE = ("mouth_inner_2", "mouth_inner_7")
OUTER_LIP_MIDDLE = ("mouth_outer_4", "mouth_outer_12")
INNER_BROWS = (("brow_l_0", "brow_l_7"), ("brow_r_0", "brow_r_7"))
SEALED_GAP = 0.02  # eye distances: an inner-lip gap below this is a closed mouth (p, b, m)
SHUT_RATIO = 0.35  # lid gap over the open level: below this an eye is shut


def lid_columns(names: Sequence[str], side: str) -> tuple[list[int], list[int]]:
    """Columns of the upper and lower lid points of :data:`EYE_PAIRS` of eye ``side`` (``l`` or
    ``r``: the image-left or image-right eye), facing pairs in the same order."""
    upper = named_points(names, [f"eye_{side}_{u}" for u, _ in EYE_PAIRS])
    lower = named_points(names, [f"eye_{side}_{lw}" for _, lw in EYE_PAIRS])
    return upper, lower


def state_signals(xy: np.ndarray, names: Sequence[str]) -> dict[str, np.ndarray]:
    """The state signals of the module docstring for every frame.

    Parameters
    ----------
    xy : (T, N, 2) or (N, 2) float
        Layout points, px.
    names : (N,) str
        Their zhang134 names.

    Returns
    -------
    dict of ``(T,)`` float64 (``()`` for one geometry): ``eye_open_l``, ``eye_open_r``,
    ``mouth_open``, ``mouth_width``, ``lip_thickness``, ``smile``, ``brow_raise``, ``brow_furrow``
    in eye distances, and ``eye_distance_px``.

    Raises
    ------
    ValueError
        A point the signals need is missing (names it).
    """
    xy = np.asarray(xy, np.float64)
    single = xy.ndim == 2
    xy = xy[None] if single else xy
    names = [str(n) for n in names]
    with np.errstate(divide="ignore", invalid="ignore"):  # a degenerate geometry (no eye distance): NaN
        out = _state_signals(xy, names)
    return {k: v[0] for k, v in out.items()} if single else out


def _state_signals(xy: np.ndarray, names: list[str]) -> dict[str, np.ndarray]:
    _, _, down, eye = eye_line_frame(xy, names)

    def along(a: np.ndarray) -> np.ndarray:
        return np.sum(a * down, axis=-1) / eye

    out = dict(expression_signals(xy, names))
    for side in "lr":
        upper, lower = lid_columns(names, side)
        out[f"eye_open_{side}"] = np.mean(np.sum((xy[:, lower] - xy[:, upper]) * down[:, None], axis=-1), axis=1) / eye
    corners = xy[:, named_points(names, MOUTH_CORNERS)]
    inner = xy[:, named_points(names, INNER_LIP_MIDDLE)]
    outer = xy[:, named_points(names, OUTER_LIP_MIDDLE)]
    out["lip_thickness"] = along(outer[:, 1] - outer[:, 0]) - along(inner[:, 1] - inner[:, 0])
    out["smile"] = -along(corners.mean(axis=1) - outer.mean(axis=1))
    inner_brows = [xy[:, named_points(names, pair)].mean(axis=1) for pair in INNER_BROWS]
    out["brow_furrow"] = np.linalg.norm(inner_brows[1] - inner_brows[0], axis=-1) / eye
    return out


@dataclass(frozen=True)
class State:
    """One expression state: a signal, how it is compared with the neutral, and when it is there.

    ``relative``: ``"ratio"`` (signal / neutral's), ``"change"`` (signal - neutral's, eye
    distances) or ``"absolute"`` (the signal itself). The state is present where the relative
    value is below ``below`` or above ``above`` (one of them is set). ``margin``: how far beyond
    a pack's covered range a demanded value must lie to count as beyond the pack.
    """

    name: str
    signal: str
    relative: str
    below: float | None = None
    above: float | None = None
    margin: float = 0.0

    def value(self, signal: np.ndarray, neutral: float) -> np.ndarray:
        """The relative value ``(T,)`` of a signal ``(T,)`` against its neutral value."""
        signal = np.asarray(signal, np.float64)
        if self.relative == "ratio":
            return signal / neutral if neutral > 0 else np.full_like(signal, np.nan)  # NaN: no neutral to compare
        if self.relative == "change":
            return signal - neutral
        return signal

    def present(self, value: np.ndarray) -> np.ndarray:
        """``(T,)`` bool: the state is there."""
        value = np.asarray(value, np.float64)
        with np.errstate(invalid="ignore"):
            return value < self.below if self.below is not None else value > self.above

    def beyond(self, value: np.ndarray, covered: tuple[float, float]) -> np.ndarray:
        """``(T,)`` bool: the state is there and goes further than ``covered`` ``(lo, hi)`` (a pack's
        range of the relative value) by more than the margin."""
        value = np.asarray(value, np.float64)
        lo, hi = covered
        with np.errstate(invalid="ignore"):
            further = value < lo - self.margin if self.below is not None else value > hi + self.margin
        return self.present(value) & further


#: The states a performance is judged by, with the thresholds the benchmarks and the run report use.
STATES = (
    State("eye_l_shut", "eye_open_l", "ratio", below=SHUT_RATIO, margin=0.15),
    State("eye_r_shut", "eye_open_r", "ratio", below=SHUT_RATIO, margin=0.15),
    State("eye_l_squint", "eye_open_l", "ratio", below=0.7, margin=0.15),
    State("eye_r_squint", "eye_open_r", "ratio", below=0.7, margin=0.15),
    State("eye_l_wide", "eye_open_l", "ratio", above=1.2, margin=0.15),
    State("eye_r_wide", "eye_open_r", "ratio", above=1.2, margin=0.15),
    State("lips_sealed", "mouth_open", "absolute", below=SEALED_GAP, margin=0.01),
    State("lips_pressed", "lip_thickness", "ratio", below=0.7, margin=0.1),
    State("pucker", "mouth_width", "ratio", below=0.88, margin=0.05),
    State("jaw_open", "mouth_open", "absolute", above=0.15, margin=0.05),
    State("smile", "smile", "change", above=0.04, margin=0.03),
    State("brow_furrow", "brow_furrow", "change", below=-0.012, margin=0.008),
    State("brow_raise", "brow_raise", "change", above=0.04, margin=0.03),
)
STATE_NAMES = tuple(s.name for s in STATES)


def state_values(xy: np.ndarray, names: Sequence[str], neutral: np.ndarray) -> dict[str, np.ndarray]:
    """The relative value of every state of :data:`STATES`, per frame.

    Parameters
    ----------
    xy : (T, N, 2) float
        Geometry per frame, px.
    names : (N,) str
    neutral : (N, 2) float
        The same face's neutral geometry, px.

    Returns
    -------
    ``{state name: (T,) float64}``.
    """
    signals = state_signals(xy, names)
    rest = state_signals(neutral, names)
    return {s.name: s.value(signals[s.signal], float(rest[s.signal])) for s in STATES}


def coverage(xy: np.ndarray, names: Sequence[str], neutral: np.ndarray) -> dict[str, tuple[float, float]]:
    """The range ``(lo, hi)`` of each state's relative value over geometries ``(K, N, 2)`` (a
    pack's example expressions and its neutral), keyed by state name."""
    values = state_values(np.concatenate([np.asarray(xy, np.float64), np.asarray(neutral, np.float64)[None]]), names, neutral)
    return {
        name: (float(np.nanmin(v)), float(np.nanmax(v))) if np.isfinite(v).any() else (np.nan, np.nan)
        for name, v in values.items()
    }


def shown(covered: Mapping[str, tuple[float, float]]) -> dict[str, bool]:
    """Per state of :data:`STATES`: does a covered range ``(lo, hi)`` (:func:`coverage`) reach
    into the state (an example shows it)?"""
    return {
        s.name: bool(s.present(np.array([covered[s.name][0] if s.below is not None else covered[s.name][1]]))[0])
        for s in STATES
        if s.name in covered
    }


def coverage_record(covered: Mapping[str, tuple[float, float]]) -> dict[str, object]:
    """A pack's coverage as ``pack.yaml`` records it: the states an example shows and those none
    shows, and the range of each state signal's relative value over the examples."""
    flags = shown(covered)
    ranges: dict[str, list[float]] = {}
    for s in STATES:
        lo, hi = covered.get(s.name, (np.nan, np.nan))
        if np.isfinite(lo) and s.signal not in ranges:
            ranges[s.signal] = [round(float(lo), 4), round(float(hi), 4)]
    return {"shows": [n for n, f in flags.items() if f], "does_not_show": [n for n, f in flags.items() if not f], "range": ranges}


def beyond_coverage(
    values: Mapping[str, np.ndarray], covered: Mapping[str, tuple[float, float]], valid: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """Per state, ``(T,)`` bool: frames whose demanded state lies beyond the covered range
    (:meth:`State.beyond`), only over ``valid`` frames; states missing from ``covered`` are skipped."""
    out = {}
    for state in STATES:
        if state.name in values and state.name in covered:
            flags = state.beyond(values[state.name], covered[state.name])
            out[state.name] = flags if valid is None else flags & np.asarray(valid, bool)
    return out
