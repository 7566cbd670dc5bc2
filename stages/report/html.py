"""The report page of ``write.report`` built from a run's bundles and frames (see
:mod:`stages.report.stage`). Kept apart from the stage's declaration so that loading a pipeline
does not import matplotlib or OpenCV."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from stages.geometry.signals import SIGNALS, follow
from stages.report import series
from stages.report.figures import Panel, dominant_heatmap, timeline
from stages.report.page import Section, image, listing, not_available, page, table
from stages.report.sheet import sheet_frames, sheet_image

FOLLOW_WARN_R = 0.5  # warn when a target signal correlates less than this with the performer's
SPANS_SHOWN = 12
TIMINGS_NOTE = ("the runner does not hand stage timings to stages (and timings would make the page differ "
                "between runs); `runner run --log-json FILE` records them")


def frame_list(flags: np.ndarray) -> str:
    """``"3-7, 12, 40-41"``: the frames where ``flags`` is True, as ranges (the first few)."""
    runs = series.spans(flags)
    text = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in runs[:SPANS_SHOWN])
    return text + (f", ... ({len(runs) - SPANS_SHOWN} more ranges)" if len(runs) > SPANS_SHOWN else "")


def reference_frame(*bundles: Mapping[str, np.ndarray] | None) -> int | None:
    """The ``neutral_frame`` the first bundle that carries one records, else None."""
    for bundle in bundles:
        if bundle is not None and "neutral_frame" in bundle:
            return int(np.asarray(bundle["neutral_frame"]))
    return None


def frame_warnings(*, no_face: np.ndarray, pose_valid: np.ndarray, limited: np.ndarray | None,
                   mapped: Mapping[str, np.ndarray] | None, warp_only: bool) -> list[str]:
    """One line per problem of the run's frames (plain text).

    Parameters
    ----------
    no_face, pose_valid : (T,) bool.
    limited : (T,) bool or None, frames soft-limited to the pack's range.
    mapped : the mapping's bundle or None (its ``lips_clamped (T,)`` is read when present).
    warp_only : every synthesis coefficient is zero.
    """
    T = len(no_face)
    flagged = [("No face in {n} of {T} frames: {f}", no_face),
               ("No valid head pose in {n} frames with a face: {f}", ~np.asarray(pose_valid, bool) & ~no_face)]
    if limited is not None:
        flagged.append(("Geometry soft-limited to the target pack's range in {n} of {T} frames: {f}", limited))
    if mapped is not None and "lips_clamped" in mapped:
        flagged.append(("Inner lips kept apart in {n} of {T} frames: {f}", np.asarray(mapped["lips_clamped"], bool)))
    lines = [text.format(n=int(flags.sum()), T=T, f=frame_list(flags)) for text, flags in flagged if flags.any()]
    if warp_only:
        lines.append("No synthesis coefficients: every subregion is zero in every frame (warp-only run)")
    return lines


def expression_section(expression: Mapping[str, Mapping[str, np.ndarray]] | None, *, reference: int,
                       shaded: Mapping[str, list[tuple[int, int]]], fps: float) -> tuple[str, dict, list[str]]:
    """The expression section's HTML, its ``follow`` numbers and its warnings (a poorly followed
    signal); ``expression`` from :func:`series.expression_series`."""
    follows, rows, warnings = {}, [], []
    for signal in SIGNALS:
        r, ratio = follow(expression[signal]["performer"], expression[signal]["target"])
        follows[signal] = {"r": r, "amplitude_ratio": ratio}
        rows.append([signal.replace("_", " "), f"{r:.2f}", f"{ratio:.2f}"])
        if np.isfinite(r) and r < FOLLOW_WARN_R:
            warnings.append(f"The target's {signal.replace('_', ' ')} follows the performer's poorly (r = {r:.2f})")
    panels = [Panel(f"{s.replace('_', ' ')} (change from frame {reference})", "eye distances",
                    {"performer": expression[s]["performer"], "target": expression[s]["target"]}, {"target": "--"})
              for s in SIGNALS]
    body = (image(timeline(panels, shaded=shaded, fps=fps), "image/png", "expression signals")
            + "<p>How well the target follows (over frames with a face): Pearson r and the amplitude ratio "
            "(target / performer standard deviation).</p>" + table(["signal", "r", "amplitude ratio"], rows))
    return body, follows, warnings


def contact_sheet(performer: Any, result: Any, frames: list[tuple[int, str]], *, height: int, fps: float) -> str:
    """The contact sheet's HTML: one captioned performer | result image per ``(frame, label)``."""
    figures = "".join(
        f"<figure>{image(sheet_image(performer, result, f, height=height), 'image/jpeg', f'frame {f}', css='')}"
        f"<figcaption>frame {f} ({f / fps:.2f} s){': ' + label if label else ''}</figcaption></figure>"
        for f, label in frames)
    return f'<div class="sheet">{figures}</div>' if figures else not_available("no frame chosen")


def report_html(inputs: Mapping[str, Any], *, evenly: int, thumb_height: int, title: str) -> str:
    """The report page of one run.

    Parameters
    ----------
    inputs : the stage's inputs: frame streams ``performer`` and ``result``; bundles ``target``,
        ``tracked`` (points), ``pose``, ``similarity``, ``coefficients``; optional
        ``displacements`` (its ``neutral_frame``) and ``mapped`` (the mapping's points with a
        per-frame soft-limit flag, see :data:`series.LIMIT_KEYS`, and ``lips_clamped``).
    evenly : evenly spaced contact-sheet frames; thumb_height : contact-sheet height, px.
    title : the page's heading.

    Returns
    -------
    The HTML document (str). Raises ValueError for inconsistent inputs.
    """
    performer, result = inputs["performer"], inputs["result"]
    T, fps = performer.info.frames, float(performer.info.fps)
    tracked, target, pose, similarity = inputs["tracked"], inputs["target"], inputs["pose"], inputs["similarity"]
    mapped, coefficients = inputs.get("mapped"), inputs["coefficients"]
    chosen = reference_frame(inputs.get("displacements"), pose)
    reference = 0 if chosen is None else chosen
    no_face = ~series.frame_valid(tracked)
    limited = series.limited_frames(mapped)
    shaded = {"no face": series.spans(no_face), "limited": [] if limited is None else series.spans(limited)}
    warnings = [f"Reference (neutral) frame: {reference}" + (
        " (recorded by the run)" if chosen is not None else " (the run records none; the pipeline takes the first frame)")]
    data: dict[str, Any] = {"frames": T, "fps": fps, "reference_frame": reference, "no_face": no_face,
                            "limited": limited}

    try:
        expression = series.expression_series(tracked, target, reference=reference)
    except ValueError as exc:
        expression, expression_body = None, not_available(str(exc))
    if expression is not None:
        expression_body, data["follow"], poorly = expression_section(expression, reference=reference, shaded=shaded,
                                                                     fps=fps)
        data["expression"] = expression
        warnings += poorly
    data["contact_sheet"] = sheet_frames(T, evenly=evenly, peaks=series.peak_frames(expression) if expression else [])

    data["head_pose"] = series.head_pose_series(pose)
    data["tracking"] = series.tracking_series(tracked)
    data["residuals"] = series.residual_series(pose, similarity)
    data["propagation"] = series.propagation_series(target)
    panels = [Panel("head pose", "degrees", data["head_pose"]),
              Panel("tracking: valid points and mean confidence", "fraction", data["tracking"]),
              Panel("fit residuals", "px", data["residuals"])]
    panels += [Panel(f"motion propagation: {key}", "px" if key.endswith("_px") else "count", {key: values})
               for key, values in data["propagation"].items()]
    geometry_body = image(timeline(panels, shaded=shaded, fps=fps), "image/png", "head pose and tracking") + (
        "" if data["propagation"] else not_available("the target points carry no propagation iterations or residual"))

    dominant = series.dominant_examples(coefficients)
    data["coefficients"] = {**dominant, "subregions": coefficients["subregions"], "examples": coefficients["examples"]}
    heatmap = dominant_heatmap(dominant["example"], dominant["weight"], subregions=coefficients["subregions"],
                               examples=coefficients["examples"], limited=limited)
    coefficient_body = image(heatmap, "image/png", "coefficients") + ("" if limited is not None else not_available(
        "the run records no per-frame range limit (connect the mapping's points to 'mapped')"))

    warnings += frame_warnings(no_face=no_face, pose_valid=pose["valid"], limited=limited, mapped=mapped,
                               warp_only=bool((dominant["example"] < 0).all()))
    data["warnings"] = warnings
    sections = [
        Section("Warnings", listing(warnings, css="warn")),
        Section("Contact sheet: performer | result",
                contact_sheet(performer, result, data["contact_sheet"], height=thumb_height, fps=fps)),
        Section("Expression: performer vs target (mouth opening, mouth width, brow raise)", expression_body),
        Section("Head pose, tracking and propagation", geometry_body),
        Section("Which example drives which subregion", coefficient_body),
        Section("Stage timings", not_available(TIMINGS_NOTE)),
    ]
    meta = (f"{T} frames at {fps:g} frames/s ({T / fps:.2f} s), performer {performer.info.width}x"
            f"{performer.info.height}, result {result.info.width}x{result.info.height}")
    return page(title=title, meta=meta, sections=sections, data=data)
