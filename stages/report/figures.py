"""The report's plots as PNG bytes (matplotlib, Agg).

Why Agg and no pyplot: the stage runs headless inside the runner (no display, possibly in a worker
thread); ``matplotlib.figure.Figure`` with an Agg canvas draws without pyplot's global figure
manager or any backend selection, so nothing global is set. Plots are drawn under matplotlib's
``default`` style, so a user's matplotlibrc cannot change them, and saved as PNG with the
``Software`` metadata removed: the same data gives the same bytes on every run (the page is
byte-identical across runs of a cached pipeline).
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import matplotlib
import matplotlib.style
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
import matplotlib.colors
from matplotlib.figure import Figure
from matplotlib.patches import Patch

WIDTH_IN, DPI = 10.0, 90
FULL_COLOUR = 0.5  # a dominant coefficient from this up is drawn in full colour
LEGEND_IN, NAMES_IN, ROW_IN = 1.8, 1.3, 0.22  # heatmap: right margin (legend), left margin (names), row height
PANEL_IN, GAP_IN, TOP_IN, BOTTOM_IN, LEFT_IN, RIGHT_IN = 1.35, 0.45, 0.75, 0.55, 0.8, 0.2  # fixed layout, inches
SHADES = {"no face": "0.82", "limited": "#f4a259"}  # span kind -> colour


@dataclass(frozen=True)
class Panel:
    """One row of a timeline figure: lines over frames sharing a y axis.

    ``lines`` maps a legend label to a ``(T,)`` float series (NaN = gap).
    """

    title: str
    ylabel: str
    lines: Mapping[str, np.ndarray]
    styles: Mapping[str, str] = field(default_factory=dict)  # label -> matplotlib format string


def fixed_figure(
    rows: float, *, gaps: int, left_in: float = LEFT_IN, right_in: float = RIGHT_IN, top_in: float = TOP_IN
) -> Figure:
    """A figure ``WIDTH_IN`` wide with ``rows`` panel heights and ``gaps`` gaps between panels,
    margins fixed in inches (cheaper than a layout engine, and stable)."""
    height = top_in + BOTTOM_IN + rows * PANEL_IN + gaps * GAP_IN
    figure = Figure(figsize=(WIDTH_IN, height), dpi=DPI)
    figure.subplots_adjust(
        left=left_in / WIDTH_IN,
        right=1 - right_in / WIDTH_IN,
        top=1 - top_in / height,
        bottom=BOTTOM_IN / height,
        hspace=GAP_IN / PANEL_IN,
    )
    return figure


def png_bytes(figure: Figure) -> bytes:
    """The figure as PNG, without the metadata that varies (software version)."""
    buffer = io.BytesIO()
    FigureCanvasAgg(figure).print_png(buffer, metadata={"Software": None})
    return buffer.getvalue()


def timeline(panels: Sequence[Panel], *, shaded: Mapping[str, Sequence[tuple[int, int]]], fps: float) -> bytes:
    """Stacked line plots over the frame index, sharing the x axis.

    Parameters
    ----------
    panels : the rows, top to bottom.
    shaded : span kind (a key of ``SHADES``) -> inclusive frame ranges to shade in every row.
    fps : frames per second, for the seconds axis on top.

    Returns
    -------
    PNG bytes.
    """
    if not panels:
        raise ValueError("a timeline needs at least one panel")
    with matplotlib.style.context("default"):
        figure = fixed_figure(len(panels), gaps=len(panels) - 1)
        axes = figure.subplots(len(panels), 1, sharex=True, squeeze=False)[:, 0]
        for ax, panel in zip(axes, panels):
            for kind, ranges in shaded.items():
                for first, last in ranges:
                    ax.axvspan(first - 0.5, last + 0.5, color=SHADES[kind], alpha=0.6, lw=0)
            for label, values in panel.lines.items():
                values = np.asarray(values, np.float64)
                ax.plot(np.arange(len(values)), values, panel.styles.get(label, "-"), label=label, lw=1.3, ms=3)
            ax.set_title(panel.title, loc="left", fontsize=10)
            ax.set_ylabel(panel.ylabel, fontsize=9)
            ax.grid(True, lw=0.4, alpha=0.5)
            handles, labels = ax.get_legend_handles_labels()
            handles += [Patch(color=SHADES[kind], alpha=0.6) for kind, ranges in shaded.items() if ranges]
            labels += [f"{kind} frames" for kind, ranges in shaded.items() if ranges]
            ax.legend(handles, labels, fontsize=8, loc="best", ncols=min(len(labels), 4), framealpha=0.8)
        axes[-1].set_xlabel("frame")
        top = axes[0].secondary_xaxis("top", functions=(lambda f: f / fps, lambda s: s * fps))
        top.set_xlabel("seconds", fontsize=9)
        return png_bytes(figure)


def example_colors(count: int) -> np.ndarray:
    """``(count, 3)`` RGB: distinct colours for the examples: tab20's ten strong colours, then its
    ten light ones, then hsv beyond 20."""
    if count > 20:
        return matplotlib.colormaps["hsv"](np.linspace(0, 1, count, endpoint=False))[:, :3]
    order = np.r_[np.arange(0, 20, 2), np.arange(1, 20, 2)][:count]
    return matplotlib.colormaps["tab20"](order)[:, :3]


def dominant_heatmap(
    example: np.ndarray, weight: np.ndarray, *, subregions: Sequence[str], examples: Sequence[str], limited: np.ndarray | None
) -> bytes:
    """Subregions (rows) over frames (columns), coloured by the example with the largest synthesis
    coefficient, in full colour from ``FULL_COLOUR`` up and paler below (white = 0, grey = no
    coefficient); with ``limited``, a last
    row marks the frames whose geometry was limited to the pack's range.

    Parameters
    ----------
    example : (T, S) int, index into ``examples``, -1 = no coefficient.
    weight : (T, S) float in [0, 1].
    subregions : (S,) names; examples : (M,) names.
    limited : (T,) bool or None.

    Returns
    -------
    PNG bytes.
    """
    T, S = example.shape
    colors = example_colors(len(examples))
    shade = np.clip(weight.T / FULL_COLOUR, 0.0, 1.0)[..., None]
    rgb = np.where((example.T >= 0)[..., None], shade * colors[example.T.clip(0)] + (1 - shade), 0.75)
    names = [str(s) for s in subregions]
    if limited is not None:
        flag = np.where(np.asarray(limited, bool)[:, None], matplotlib.colors.to_rgb(SHADES["limited"]), 1.0)
        rgb = np.concatenate([rgb, np.ones((1, T, 3)), flag[None]], axis=0)  # a blank row, then the flags
        names += ["", "range limited"]
    with matplotlib.style.context("default"):
        figure = fixed_figure(ROW_IN * len(names) / PANEL_IN, gaps=0, left_in=NAMES_IN, right_in=LEGEND_IN, top_in=0.35)
        ax = figure.subplots()
        ax.imshow(rgb, aspect="auto", interpolation="nearest", extent=(-0.5, T - 0.5, len(names) - 0.5, -0.5))
        ax.set_yticks(range(len(names)), names, fontsize=8)
        ax.set_xlabel("frame")
        ax.set_title(
            f"example with the largest coefficient per subregion (paler: coefficient below {FULL_COLOUR:g})",
            loc="left",
            fontsize=10,
        )
        used = sorted(set(example[example >= 0].tolist()))
        if used:
            ax.legend(
                handles=[Patch(color=colors[i], label=str(examples[i])) for i in used],
                loc="upper left",
                bbox_to_anchor=(1.01, 1.0),
                fontsize=8,
                title="example",
                title_fontsize=8,
            )
        return png_bytes(figure)


def flag_strip(flags: Mapping[str, np.ndarray], *, judged: np.ndarray, title: str, colour: str) -> bytes:
    """Rows of per-frame flags over the frame index: ``colour`` where a row's flag is set,
    white where not, grey where the frame was not judged.

    Parameters
    ----------
    flags : row name -> ``(T,)`` bool, top to bottom.
    judged : (T,) bool.
    title : the plot's title; colour : a matplotlib colour.

    Returns
    -------
    PNG bytes.
    """
    names = list(flags)
    on = np.array([np.asarray(flags[n], bool) for n in names]).reshape(len(names), len(judged))
    rgb = np.where(on[..., None], matplotlib.colors.to_rgb(colour), 1.0)
    rgb = np.where(np.asarray(judged, bool)[None, :, None], rgb, 0.75)
    T = len(judged)
    with matplotlib.style.context("default"):
        figure = fixed_figure(ROW_IN * max(len(names), 1) / PANEL_IN, gaps=0, left_in=NAMES_IN, top_in=0.35)
        ax = figure.subplots()
        ax.imshow(rgb, aspect="auto", interpolation="nearest", extent=(-0.5, T - 0.5, len(names) - 0.5, -0.5))
        ax.set_yticks(range(len(names)), names, fontsize=8)
        ax.set_xlabel("frame")
        ax.set_title(title, loc="left", fontsize=10)
        return png_bytes(figure)
