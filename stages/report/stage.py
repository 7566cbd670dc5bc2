"""``write.report``: one self-contained HTML page to judge a run (``<out>/<stage>/index.html``).

The page shows a contact sheet (performer | result at evenly spaced frames and at the expression
peaks), performer vs target expression signals, head pose, tracking validity and fit residuals,
the motion propagation's iterations and residual (Sec. 10.1), which example drives which
subregion (the coefficients of eq. 2-5), the frames whose geometry left the target pack's range,
and the run's warnings. Everything comes from the run's own data and is drawn deterministically,
so a cached run's report is byte-identical and costs only its own (cheap) recomputation.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from runner.stage import Context, Param, SequenceStage, StageError
from stages.geometry.signals import SIGNALS, follow
from stages.report import series
from stages.report.figures import Panel, dominant_heatmap, timeline
from stages.report.page import Section, image, listing, not_available, page, table
from stages.report.sheet import sheet_frames, sheet_image
from stages.writers.atomic import atomic_write
from stages.writers.bundles import check_bundle

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
    info = performer.info
    T, fps = info.frames, float(info.fps)
    tracked, target, pose, similarity = inputs["tracked"], inputs["target"], inputs["pose"], inputs["similarity"]
    displacements, mapped = inputs.get("displacements"), inputs.get("mapped")
    chosen = reference_frame(displacements, pose)
    reference = 0 if chosen is None else chosen
    no_face = ~series.frame_valid(tracked)
    limited = series.limited_frames(mapped)
    shaded = {"no face": series.spans(no_face), "limited": [] if limited is None else series.spans(limited)}
    data: dict[str, Any] = {"frames": T, "fps": fps, "reference_frame": reference, "no_face": no_face}
    warnings = [f"Reference (neutral) frame: {reference}" + (
        " (recorded by the run)" if chosen is not None else " (the run records none; the pipeline takes the first frame)")]
    sections = []

    # Expression signals, then the contact sheet at their peaks (shown first).
    try:
        expression = series.expression_series(tracked, target, reference=reference)
    except ValueError as exc:
        expression, expression_body = None, not_available(str(exc))
    if expression is not None:
        data["expression"] = expression
        data["follow"] = {}
        rows = []
        for signal in SIGNALS:
            r, ratio = follow(expression[signal]["performer"], expression[signal]["target"])
            data["follow"][signal] = {"r": r, "amplitude_ratio": ratio}
            rows.append([signal.replace("_", " "), f"{r:.2f}", f"{ratio:.2f}"])
            if np.isfinite(r) and r < FOLLOW_WARN_R:
                warnings.append(f"The target's {signal.replace('_', ' ')} follows the performer's poorly (r = {r:.2f})")
        panels = [Panel(f"{s.replace('_', ' ')} (change from frame {reference})", "eye distances",
                        {"performer": expression[s]["performer"], "target": expression[s]["target"]},
                        {"target": "--"}) for s in SIGNALS]
        expression_body = (image(timeline(panels, shaded=shaded, fps=fps), "image/png", "expression signals")
                           + "<p>How well the target follows (over frames with a face): Pearson r and the "
                           "amplitude ratio (target / performer standard deviation).</p>"
                           + table(["signal", "r", "amplitude ratio"], rows))
    chosen_frames = sheet_frames(T, evenly=evenly, peaks=series.peak_frames(expression) if expression else [])
    data["contact_sheet"] = chosen_frames
    figures = "".join(
        f"<figure>{image(sheet_image(performer, result, f, height=thumb_height), 'image/jpeg', f'frame {f}', css='')}"
        f"<figcaption>frame {f} ({f / fps:.2f} s){': ' + label if label else ''}</figcaption></figure>"
        for f, label in chosen_frames)
    sections.append(Section("Contact sheet: performer | result",
                            f'<div class="sheet">{figures}</div>' if figures else not_available("no frame chosen")))
    sections.append(Section("Expression: performer vs target (mouth opening, mouth width, brow raise)",
                            expression_body))

    # Head pose, tracking, residuals, propagation.
    data["head_pose"] = series.head_pose_series(pose)
    data["tracking"] = series.tracking_series(tracked)
    data["residuals"] = series.residual_series(pose, similarity)
    data["propagation"] = series.propagation_series(target)
    panels = [Panel("head pose", "degrees", data["head_pose"]),
              Panel("tracking: valid points and mean confidence", "fraction", data["tracking"]),
              Panel("fit residuals", "px", data["residuals"])]
    panels += [Panel(f"motion propagation: {key.replace('_', ' ')}", key.split("_")[-1] if "px" in key else "count",
                     {key: values}) for key, values in data["propagation"].items()]
    sections.append(Section("Head pose, tracking and propagation",
                            image(timeline(panels, shaded=shaded, fps=fps), "image/png", "head pose and tracking")
                            + ("" if data["propagation"] else not_available(
                                "the target points carry no propagation iterations or residual"))))

    # Synthesis coefficients and the pack's range.
    coefficients = inputs["coefficients"]
    dominant = series.dominant_examples(coefficients)
    data["coefficients"] = {**dominant, "subregions": coefficients["subregions"], "examples": coefficients["examples"]}
    data["limited"] = limited
    heatmap = dominant_heatmap(dominant["example"], dominant["weight"], subregions=coefficients["subregions"],
                               examples=coefficients["examples"], limited=limited)
    sections.append(Section("Which example drives which subregion", image(heatmap, "image/png", "coefficients")
                            + ("" if limited is not None else not_available(
                                "the run records no per-frame range limit (connect the mapping's points to 'mapped')"))))

    # Warnings and timings.
    if no_face.any():
        warnings.append(f"No face in {int(no_face.sum())} of {T} frames: {frame_list(no_face)}")
    bad_pose = ~np.asarray(pose["valid"], bool) & ~no_face
    if bad_pose.any():
        warnings.append(f"No valid head pose in {int(bad_pose.sum())} frames with a face: {frame_list(bad_pose)}")
    if limited is not None and limited.any():
        warnings.append(f"Geometry soft-limited to the target pack's range in {int(limited.sum())} of {T} frames: "
                        f"{frame_list(limited)}")
    if mapped is not None and "lips_clamped" in mapped and np.asarray(mapped["lips_clamped"], bool).any():
        clamped = np.asarray(mapped["lips_clamped"], bool)
        warnings.append(f"Inner lips kept apart in {int(clamped.sum())} frames: {frame_list(clamped)}")
    if (dominant["example"] < 0).all():
        warnings.append("No synthesis coefficients: every subregion is zero in every frame (warp-only run)")
    data["warnings"] = warnings
    sections.insert(0, Section("Warnings", listing(warnings, css="warn")))
    sections.append(Section("Stage timings", not_available(TIMINGS_NOTE)))
    meta = (f"{T} frames at {fps:g} frames/s ({T / fps:.2f} s), performer {info.width}x{info.height}, "
            f"result {result.info.width}x{result.info.height}")
    return page(title=title, meta=meta, sections=sections, data=data)


class WriteReport(SequenceStage):
    """``write.report``: ``index.html`` under the ``report`` files output (see the module doc)."""

    name = "write.report"
    version = "1"
    doc = "an HTML page to judge the run: contact sheet, expression/pose/tracking curves, coefficients, warnings"
    inputs = {
        "performer": "frames", "result": "frames", "target": "points", "tracked": "points", "pose": "pose",
        "similarity": "similarity", "coefficients": "coefficients", "displacements": "displacements",
        "mapped": "points",
    }
    optional_inputs = frozenset({"displacements", "mapped"})
    outputs = {"report": "files"}
    params = (
        Param("sheet_frames", int, 8, "evenly spaced contact-sheet frames (the expression peaks are added)",
              min=0, max=200),
        Param("thumb_height", int, 180, "contact-sheet image height, px", min=16, max=2160),
        Param("title", str, "Expression mapping: run report", "the page's heading"),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        frames = inputs["performer"].info.frames
        if inputs["result"].info.frames != frames:
            raise StageError(f"{self.name}: input 'result' has {inputs['result'].info.frames} frames, "
                             f"'performer' has {frames}")
        for port, kind in (("target", "points"), ("tracked", "points"), ("pose", "pose"),
                           ("similarity", "similarity"), ("coefficients", "coefficients"), ("mapped", "points")):
            if inputs.get(port) is not None:
                check_bundle(inputs[port], stage=self.name, port=port, kind=kind, frames=frames)
        try:
            text = report_html(inputs, evenly=int(params["sheet_frames"]), thumb_height=int(params["thumb_height"]),
                               title=str(params["title"]))
        except (KeyError, ValueError) as exc:
            raise StageError(f"{self.name}: {exc}") from None
        folder = Path(ctx.files_dir("report"))
        folder.mkdir(parents=True, exist_ok=True)
        with atomic_write(folder / "index.html") as tmp:
            Path(tmp).write_text(text, encoding="utf-8")
        ctx.progress(frames)
        return {"report": None}
