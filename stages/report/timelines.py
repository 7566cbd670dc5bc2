"""The report's two timelines (matplotlib), drawn from the geometry alone, and their bundle.

The expression timeline (performer vs target signals) and the head pose / tracking / propagation
timeline need no synthesis output, so ``report.figures`` (:class:`stages.report.stage.ReportFigures`)
draws them while the result is synthesized and ``write.report`` embeds them as they are; without
that stage, ``write.report`` draws them itself with the same functions (the same bytes).

The ``figures`` bundle: ``expression (N1,) uint8`` and ``geometry (N2,) uint8`` (the two PNG
files; no ``expression`` when the geometries have no expression signal), ``frames ()`` (the frame
count T they were drawn for) and ``fps ()`` (the frame rate of their seconds axis).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from stages.geometry.signals import SIGNALS
from stages.report.figures import Panel, timeline
from stages.report.series import GeometrySeries

PLOTS = ("expression", "geometry")  # the bundle's PNG fields, in page order


def expression_plot(expression: Mapping[str, Mapping[str, np.ndarray]], *, reference: int,
                    shaded: Mapping[str, list[tuple[int, int]]], fps: float) -> bytes:
    """The expression timeline as PNG bytes: one panel per signal, performer and target.

    Parameters
    ----------
    expression : ``{signal: {"performer": (T,), "target": (T,)}}`` from
        :func:`stages.report.series.expression_series` (eye distances, change from ``reference``).
    reference : the reference (neutral) frame, for the panel titles.
    shaded : span kind -> inclusive frame ranges shaded in every panel.
    fps : frames per second (the seconds axis).
    """
    panels = [Panel(f"{s.replace('_', ' ')} (change from frame {reference})", "eye distances",
                    {"performer": expression[s]["performer"], "target": expression[s]["target"]}, {"target": "--"})
              for s in SIGNALS]
    return timeline(panels, shaded=shaded, fps=fps)


def geometry_plot(series: GeometrySeries, *, fps: float) -> bytes:
    """The head pose, tracking and propagation timeline as PNG bytes (``fps``: the seconds axis)."""
    panels = [Panel("head pose", "degrees", series.head_pose),
              Panel("tracking: valid points and mean confidence", "fraction", series.tracking),
              Panel("fit residuals", "px", series.residuals)]
    panels += [Panel(f"motion propagation: {key}", "px" if key.endswith("_px") else "count", {key: values})
               for key, values in series.propagation.items()]
    return timeline(panels, shaded=series.shaded, fps=fps)


def timeline_plots(series: GeometrySeries, *, fps: float) -> dict[str, bytes]:
    """``{"expression": PNG, "geometry": PNG}``; no ``expression`` when ``series`` has none."""
    plots = {}
    if series.expression is not None:
        plots["expression"] = expression_plot(series.expression, reference=series.reference, shaded=series.shaded,
                                              fps=fps)
    plots["geometry"] = geometry_plot(series, fps=fps)
    return plots


def figures_bundle(plots: Mapping[str, bytes], *, frames: int, fps: float) -> dict[str, np.ndarray]:
    """The ``figures`` bundle (module docstring) of :func:`timeline_plots`' PNGs."""
    return {**{name: np.frombuffer(png, np.uint8) for name, png in plots.items()},
            "frames": np.array(frames, np.int64), "fps": np.array(fps, np.float64)}


def bundle_plots(bundle: Mapping[str, np.ndarray], *, frames: int, fps: float, expression: bool) -> dict[str, bytes]:
    """The PNGs of a ``figures`` bundle, checked against the page they go into.

    Parameters
    ----------
    bundle : the ``figures`` bundle.
    frames, fps : the page's frame count and rate (its contact sheet's).
    expression : whether the page has an expression timeline.

    Raises
    ------
    ValueError
        The plots were drawn for another frame count or rate, or the expression plot is missing.
    """
    drawn = (int(bundle["frames"]), float(bundle["fps"]))
    if drawn != (frames, fps):
        raise ValueError(f"figures: drawn for {drawn[0]} frames at {drawn[1]:g} frames/s, the contact sheet has "
                         f"{frames} frames at {fps:g} frames/s (set the figures stage's fps to the clip's)")
    needed = [name for name in PLOTS if name != "expression" or expression]
    missing = [name for name in needed if name not in bundle]
    if missing:
        raise ValueError(f"figures: no {' and no '.join(missing)} plot, which this page shows")
    return {name: np.asarray(bundle[name], np.uint8).tobytes() for name in needed}
