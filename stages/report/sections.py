"""The report's plotted sections (matplotlib): expression, head pose / tracking / propagation, and
which example drives which subregion.

:func:`stages.report.html.report_html` imports this module when it draws a page, so that loading a
pipeline does not import matplotlib (about 1.4 s of one core).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from stages.geometry.signals import SIGNALS, follow
from stages.report.figures import Panel, dominant_heatmap, flag_strip, timeline
from stages.report.page import image, not_available, table

FOLLOW_WARN_R = 0.5  # warn when a target signal correlates less than this with the performer's


def expression_section(
    expression: Mapping[str, Mapping[str, np.ndarray]], *, reference: int, shaded: Mapping[str, list[tuple[int, int]]], fps: float
) -> tuple[str, dict, list[str]]:
    """The expression section's HTML, its ``follow`` numbers and its warnings (a poorly followed
    signal).

    Parameters
    ----------
    expression : ``{signal: {"performer": (T,), "target": (T,)}}`` from
        :func:`stages.report.series.expression_series` (eye distances, change from ``reference``).
    reference : the reference (neutral) frame, for the panel titles.
    shaded : span kind -> inclusive frame ranges shaded in every panel.
    fps : frames per second (the seconds axis).
    """
    follows, rows, warnings = {}, [], []
    for signal in SIGNALS:
        r, ratio = follow(expression[signal]["performer"], expression[signal]["target"])
        follows[signal] = {"r": r, "amplitude_ratio": ratio}
        rows.append([signal.replace("_", " "), f"{r:.2f}", f"{ratio:.2f}"])
        if np.isfinite(r) and r < FOLLOW_WARN_R:
            warnings.append(f"The target's {signal.replace('_', ' ')} follows the performer's poorly (r = {r:.2f})")
    panels = [
        Panel(
            f"{s.replace('_', ' ')} (change from frame {reference})",
            "eye distances",
            {"performer": expression[s]["performer"], "target": expression[s]["target"]},
            {"target": "--"},
        )
        for s in SIGNALS
    ]
    body = (
        image(timeline(panels, shaded=shaded, fps=fps), "image/png", "expression signals")
        + "<p>How well the target follows (over frames with a face): Pearson r and the amplitude ratio "
        "(target / performer standard deviation).</p>" + table(["signal", "r", "amplitude ratio"], rows)
    )
    return body, follows, warnings


def states_section(
    states: Mapping[str, Mapping[str, np.ndarray]],
    mapped: Mapping[str, np.ndarray] | None,
    *,
    shaded: Mapping[str, list[tuple[int, int]]],
    fps: float,
    frame_list: Any,
) -> tuple[str, list[str]]:
    """The expression-states section: eye and lip-seal curves, and the states the performance
    demands beyond what the target pack's examples show, with their frames.

    Parameters
    ----------
    states : :func:`stages.report.series.state_series`.
    mapped : the mapping's points bundle (``state_names (S,)``, ``beyond_pack (T, S)``,
        ``coverage (S, 2)``) or None.
    shaded, fps : as for :func:`expression_section`.
    frame_list : ``(T,) bool -> str``, frame ranges as the page writes them.
    """
    from stages.geometry.states import SEALED_GAP

    panels = [
        Panel(
            f"{'image-left' if side == 'l' else 'image-right'} eye: lid gap",
            "eye distances",
            {"performer": states[f"eye_open_{side}"]["performer"], "target": states[f"eye_open_{side}"]["target"]},
            {"target": "--"},
        )
        for side in "lr"
    ]
    panels.append(
        Panel(
            f"inner-lip gap (lips sealed below {SEALED_GAP:g})",
            "eye distances",
            {
                "performer": states["mouth_open"]["performer"],
                "target": states["mouth_open"]["target"],
                "sealed": np.full(len(states["mouth_open"]["target"]), SEALED_GAP),
            },
            {"target": "--", "sealed": ":"},
        )
    )
    body = image(timeline(panels, shaded=shaded, fps=fps), "image/png", "eye and lip states")
    warnings: list[str] = []
    if mapped is None or "beyond_pack" not in mapped:
        return body + not_available(
            "the run records no states beyond the pack (connect the mapping's points to 'mapped')"
        ), warnings
    names = [str(n) for n in mapped["state_names"]]
    beyond = np.asarray(mapped["beyond_pack"], bool)
    covered = np.asarray(mapped["coverage"], np.float64)
    rows = []
    for k, name in enumerate(names):
        rows.append(
            [
                name.replace("_", " "),
                f"{covered[k, 0]:.2f} .. {covered[k, 1]:.2f}",
                str(int(beyond[:, k].sum())),
                frame_list(beyond[:, k]) if beyond[:, k].any() else "",
            ]
        )
        if beyond[:, k].any():
            warnings.append(
                f"Beyond what the target pack's examples show: {name.replace('_', ' ')} in "
                f"{int(beyond[:, k].sum())} frames (the warp makes the geometry, the texture is the "
                f"nearest example's)"
            )
    body += (
        "<p>What the target pack's example expressions cover of each state (the range of its relative value: "
        "lid gap over the neutral's, mouth opening in eye distances, change from the neutral) and the frames "
        "where the performance goes beyond it.</p>" + table(["state", "pack covers", "frames beyond", "frames"], rows)
    )
    return body, warnings


def geometry_section(data: Mapping[str, Any], *, shaded: Mapping[str, list[tuple[int, int]]], fps: float) -> str:
    """The head pose, tracking and propagation section's HTML.

    Parameters
    ----------
    data : the page's series: ``head_pose``, ``tracking``, ``residuals``, ``propagation`` (each
        name -> ``(T,)``, see :mod:`stages.report.series`).
    shaded, fps : as for :func:`expression_section`.
    """
    panels = [
        Panel("head pose", "degrees", data["head_pose"]),
        Panel("tracking: valid points and mean confidence", "fraction", data["tracking"]),
        Panel("fit residuals", "px", data["residuals"]),
    ]
    panels += [
        Panel(f"motion propagation: {key}", "px" if key.endswith("_px") else "count", {key: values})
        for key, values in data["propagation"].items()
    ]
    return image(timeline(panels, shaded=shaded, fps=fps), "image/png", "head pose and tracking") + (
        "" if data["propagation"] else not_available("the target points carry no propagation iterations or residual")
    )


def coefficient_section(
    dominant: Mapping[str, np.ndarray], coefficients: Mapping[str, np.ndarray], *, limited: np.ndarray | None
) -> str:
    """The "which example drives which subregion" section's HTML.

    Parameters
    ----------
    dominant : ``example (T, S)``, ``weight (T, S)`` from :func:`stages.report.series.dominant_examples`.
    coefficients : the coefficients bundle (its ``subregions (S,)`` and ``examples (M,)`` names).
    limited : (T,) bool, the soft-limited frames, or None when the run records none.
    """
    heatmap = dominant_heatmap(
        dominant["example"],
        dominant["weight"],
        subregions=coefficients["subregions"],
        examples=coefficients["examples"],
        limited=limited,
    )
    return image(heatmap, "image/png", "coefficients") + (
        ""
        if limited is not None
        else not_available("the run records no per-frame range limit (connect the mapping's points to 'mapped')")
    )


def occlusion_section(occlusion: Mapping[str, np.ndarray], ranges: Mapping[str, str]) -> str:
    """The occlusion section's HTML: a strip per face region over the frames (hidden frames
    coloured) and a table of counts.

    Parameters
    ----------
    occlusion : the ``occlusion`` bundle (``regions (R,)``, ``occluded (T, R)``, ``valid (T,)``).
    ranges : region -> its occluded frames as text (first ranges).
    """
    regions = [str(r) for r in occlusion["regions"]]
    occluded, judged = np.asarray(occlusion["occluded"], bool), np.asarray(occlusion["valid"], bool)
    strip = flag_strip(
        {r: occluded[:, k] for k, r in enumerate(regions)},
        judged=judged,
        title="occluded face regions (grey: frame not judged)",
        colour="#c0392b",
    )
    rows = [[r, str(int(occluded[:, k].sum())), ranges[r] or "none"] for k, r in enumerate(regions)]
    return (
        image(strip, "image/png", "occluded face regions")
        + f"<p>Frames judged: {int(judged.sum())} of {len(judged)}.</p>"
        + table(["region", "occluded frames", "frames"], rows)
    )
