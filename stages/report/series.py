"""The numbers a run report shows, computed from the run's own bundles (pure functions).

Every curve of the page comes from here, so a test can check it against the input bundles and the
page can embed exactly what it plots. All series have one value per frame (``T``); a value that
does not exist for a frame (no face, invalid pose) is NaN.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from stages.geometry.rotation import ypr_yxz
from stages.geometry.signals import BROWS, LOWER_INNER_LIP, SIGNALS, UPPER_INNER_LIP, expression_signals

# Point groups whose members expression_signals averages: a geometry may carry only some of them
# (the paper's tracked subset has mouth_inner_2, mouth_inner_7 and four points per brow).
AVERAGED_GROUPS = (UPPER_INNER_LIP, LOWER_INNER_LIP, BROWS)
LIMIT_KEYS = ("range_limited", "limited")  # map.expression's per-frame soft-limit flag, then the generic name
PEAK_MIN = 0.02  # eye distances: a smaller change from neutral is not an expression peak


def shared_signal_points(*name_lists: Sequence[str]) -> tuple[str, ...]:
    """Names of the averaged signal points (lips, brows) that every geometry has.

    Parameters
    ----------
    *name_lists : the ``names (N,)`` of each geometry.

    Returns
    -------
    The members of ``AVERAGED_GROUPS`` present in all lists, in group order.

    Raises
    ------
    ValueError
        A group has no member common to all the geometries.
    """
    present = set.intersection(*(set(map(str, names)) for names in name_lists))
    shared = []
    for group in AVERAGED_GROUPS:
        members = [name for name in group if name in present]
        if not members:
            raise ValueError(f"expression signals need one of {list(group)} in every geometry; none is shared")
        shared += members
    return tuple(shared)


def signals_over(xy: np.ndarray, names: Sequence[str], keep: Sequence[str]) -> dict[str, np.ndarray]:
    """:func:`stages.geometry.signals.expression_signals` with each averaged group restricted to
    the points ``keep``, so that two geometries with different point sets are measured alike.

    Each point of a group outside ``keep`` is replaced by the mean of the group's kept points,
    which leaves the group's mean equal to the mean over the kept points.

    Parameters
    ----------
    xy : (T, N, 2) float, px
    names : (N,) str, layout names
    keep : averaged-group members to use (see :func:`shared_signal_points`)

    Returns
    -------
    ``mouth_open``, ``mouth_width``, ``brow_raise``, ``eye_distance_px``: each ``(T,)``, in eye
    distances (the last in px).
    """
    names = [str(n) for n in names]
    where = {n: i for i, n in enumerate(names)}
    xy = np.asarray(xy, np.float64)
    extra_names, extra = [], []
    for group in AVERAGED_GROUPS:
        kept = [where[n] for n in group if n in keep and n in where]
        if not kept:
            raise ValueError(f"none of {list(group)} is both kept and in the geometry")
        mean = xy[:, kept].mean(axis=1)
        for name in group:
            if name not in keep:
                extra_names.append(name)
                extra.append(mean)
    drop = [i for i, n in enumerate(names) if n in extra_names]
    base_names = [n for i, n in enumerate(names) if i not in drop]
    base = np.delete(xy, drop, axis=1)
    filled = np.concatenate([base, np.stack(extra, axis=1)], axis=1) if extra else base
    return expression_signals(filled, base_names + extra_names)


def reference_frame(*bundles: Mapping[str, np.ndarray] | None) -> int | None:
    """The frame the expression curves are read from: the first bundle's
    ``neutral_nearest_frame`` (the frame closest to a neutral estimated from the clip), else its
    ``neutral_frame``; None when no bundle records one."""
    for bundle in bundles:
        for key in ("neutral_nearest_frame", "neutral_frame"):
            if bundle is not None and key in bundle:
                return int(np.asarray(bundle[key]))
    return None


def state_series(performer: Mapping[str, np.ndarray], target: Mapping[str, np.ndarray]) -> dict[str, dict[str, np.ndarray]]:
    """Each eye's lid gap and the inner-lip gap of performer and target, in each face's eye
    distances (:func:`stages.geometry.states.state_signals`), NaN on frames without a face;
    ``{signal: {"performer": (T,), "target": (T,)}}`` for ``eye_open_l``, ``eye_open_r``,
    ``mouth_open``. Raises ValueError when a geometry lacks the lid or lip points."""
    from stages.geometry.states import state_signals

    out: dict[str, dict[str, np.ndarray]] = {k: {} for k in ("eye_open_l", "eye_open_r", "mouth_open")}
    for role, bundle in (("performer", performer), ("target", target)):
        values = state_signals(np.asarray(bundle["xy"], np.float64), [str(n) for n in bundle["names"]])
        face = frame_valid(bundle)
        for key in out:
            out[key][role] = np.where(face, values[key], np.nan)
    return out


def frame_valid(points: Mapping[str, np.ndarray]) -> np.ndarray:
    """``(T,)`` bool: frames where a ``points`` bundle has at least one valid point (a face)."""
    return np.asarray(points["valid"], bool).any(axis=1)


def expression_series(
    performer: Mapping[str, np.ndarray], target: Mapping[str, np.ndarray], *, reference: int
) -> dict[str, dict[str, np.ndarray]]:
    """Performer and target expression signals, as change from the reference (neutral) frame.

    Parameters
    ----------
    performer, target : ``points`` bundles (``xy (T, N, 2)``, ``valid (T, N)``, ``names (N,)``).
    reference : the neutral frame index; both signals are given minus their value there.

    Returns
    -------
    ``{signal: {"performer": (T,), "target": (T,)}}`` for each of ``SIGNALS`` (eye distances;
    NaN on frames without a face in that geometry).
    """
    keep = shared_signal_points(performer["names"], target["names"])
    out: dict[str, dict[str, np.ndarray]] = {signal: {} for signal in SIGNALS}
    for role, bundle in (("performer", performer), ("target", target)):
        values = signals_over(bundle["xy"], bundle["names"], keep)
        face = frame_valid(bundle)
        for signal in SIGNALS:
            series = values[signal] - values[signal][reference]
            out[signal][role] = np.where(face, series, np.nan)
    return out


def head_pose_series(pose: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Yaw, pitch, roll in degrees per frame (NaN where the pose is invalid).

    Uses the bundle's ``ypr_deg (T, 3)`` when present, else :func:`ypr_yxz` of
    ``R (T, 3, 3)`` (``R = Ry Rx Rz``).
    """
    if "ypr_deg" in pose:
        ypr = np.asarray(pose["ypr_deg"], np.float64)
    else:
        ypr = ypr_yxz(np.asarray(pose["R"], np.float64))
    ypr = np.where(np.asarray(pose["valid"], bool)[:, None], ypr, np.nan)
    return {"yaw": ypr[:, 0], "pitch": ypr[:, 1], "roll": ypr[:, 2]}


def tracking_series(tracked: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per frame: fraction of the tracked points that are valid, and their mean confidence when
    the bundle carries ``confidence (T, N)`` (over valid points; NaN where none is valid)."""
    valid = np.asarray(tracked["valid"], bool)
    out = {"valid_fraction": valid.mean(axis=1)}
    if "confidence" in tracked:
        confidence = np.where(valid, np.asarray(tracked["confidence"], np.float64), np.nan)
        count = valid.sum(axis=1)
        total = np.nansum(confidence, axis=1)
        out["mean_confidence"] = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return out


def residual_series(pose: Mapping[str, np.ndarray], similarity: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Fit residuals per frame, px: the pose's reprojection error and the 2D similarity's residual
    (eq. 8-9), NaN where that fit is invalid."""
    return {
        "pose_reproj_err_px": np.where(np.asarray(pose["valid"], bool), np.asarray(pose["reproj_err_px"], np.float64), np.nan),
        "similarity_residual_px": np.where(
            np.asarray(similarity["valid"], bool), np.asarray(similarity["residual_px"], np.float64), np.nan
        ),
    }


def propagation_series(target: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Motion propagation per frame (Sec. 10.1): ``iterations`` and ``input_error_px`` as
    ``propagate.hierarchical`` records them in its ``points`` output; empty if absent."""
    return {key: np.asarray(target[key], np.float64) for key in ("iterations", "input_error_px") if key in target}


def limited_frames(mapped: Mapping[str, np.ndarray] | None) -> np.ndarray | None:
    """``(T,)`` bool: frames whose geometry was soft-limited to the pack's range, from the first of
    ``LIMIT_KEYS`` the mapping bundle carries; None when there is none."""
    if mapped is None:
        return None
    key = next((k for k in LIMIT_KEYS if k in mapped), None)
    return None if key is None else np.asarray(mapped[key], bool)


def dominant_examples(coefficients: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Which example drives each subregion in each frame (the synthesis coefficients of eq. 2-5).

    Parameters
    ----------
    coefficients : ``coeff (T, S, M)`` (NaN where an example is not a candidate of the
        subregion), ``subregions (S,)``, ``examples (M,)``.

    Returns
    -------
    ``example (T, S)`` int, the index of the largest coefficient, -1 where all are zero or NaN
    (warp-only); ``weight (T, S)`` float, that coefficient (0 where -1).
    """
    coeff = np.nan_to_num(np.asarray(coefficients["coeff"], np.float64), nan=0.0)
    if coeff.ndim != 3 or coeff.shape[1:] != (len(coefficients["subregions"]), len(coefficients["examples"])):
        raise ValueError(f"coefficients 'coeff' must be (T, S, M) with S subregions and M examples, got {coeff.shape}")
    index = coeff.argmax(axis=2)
    weight = np.take_along_axis(coeff, index[..., None], axis=2)[..., 0]
    return {"example": np.where(weight > 0, index, -1), "weight": np.where(weight > 0, weight, 0.0)}


def peak_frames(signals: Mapping[str, Mapping[str, np.ndarray]], *, least: float = PEAK_MIN) -> list[tuple[int, str]]:
    """Frames where the expression peaks: the maximum and minimum of each signal's change from
    neutral, from the performer's series where it has any finite value, else the target's; a
    maximum below ``least`` or a minimum above ``-least`` (eye distances) is no peak.

    Returns
    -------
    ``[(frame, label)]`` sorted by frame, one entry per frame (labels of coinciding peaks joined).
    """
    labels: dict[int, list[str]] = {}
    for signal, roles in signals.items():
        series = roles["performer"] if np.isfinite(roles["performer"]).any() else roles["target"]
        if not np.isfinite(series).any():
            continue
        for word, frame, sign in (("max", np.nanargmax(series), 1), ("min", np.nanargmin(series), -1)):
            if sign * series[frame] >= least:
                labels.setdefault(int(frame), []).append(f"{signal.replace('_', ' ')} {word}")
    return [(frame, ", ".join(names)) for frame, names in sorted(labels.items())]


def spans(flags: np.ndarray) -> list[tuple[int, int]]:
    """Runs of True in a ``(T,)`` bool array as ``[(first, last)]`` inclusive frame ranges."""
    flags = np.asarray(flags, bool)
    edges = np.diff(np.concatenate([[0], flags.astype(np.int8), [0]]))
    return [(int(a), int(b) - 1) for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1))]
