"""The report page of ``write.report`` built from a run's bundles and frames (see
:mod:`stages.report.stage`). Kept apart from the stage's declaration so that loading a pipeline
does not import matplotlib or OpenCV.

The contact sheet's frames (decoded and, in a run, synthesized again: PyAV, torch and OpenCV
release the GIL) are read and encoded on worker threads (``sheet_threads``) while this thread
imports matplotlib and draws the plots (:mod:`stages.report.sections`). The page is the same as
built one part after the other: matplotlib is used on this thread only, the workers touch none
of it, and each frame's image depends on that frame alone.
"""

from __future__ import annotations

from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from stages.report import series
from stages.report.page import Section, image, listing, not_available, page
from stages.report.sheet import sheet_frames, sheet_image

SHEET_THREADS = 2  # contact-sheet frames read at once, besides this thread drawing the plots
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


def contact_sheet(frames: list[tuple[int, str]], images: list[bytes], *, fps: float) -> str:
    """The contact sheet's HTML: one captioned image per ``(frame, label)`` of ``frames``;
    ``images`` are their performer | result JPEGs (:func:`stages.report.sheet.sheet_image`), in
    the same order."""
    figures = "".join(
        f"<figure>{image(jpeg, 'image/jpeg', f'frame {f}', css='')}"
        f"<figcaption>frame {f} ({f / fps:.2f} s){': ' + label if label else ''}</figcaption></figure>"
        for (f, label), jpeg in zip(frames, images, strict=True))
    return f'<div class="sheet">{figures}</div>' if figures else not_available("no frame chosen")


def report_html(inputs: Mapping[str, Any], *, evenly: int, thumb_height: int, title: str,
                sheet_threads: int = SHEET_THREADS) -> str:
    """The report page of one run.

    Parameters
    ----------
    inputs : the stage's inputs: frame streams ``performer`` and ``result``; bundles ``target``,
        ``tracked`` (points), ``pose``, ``similarity``, ``coefficients``; optional
        ``displacements`` (its ``neutral_frame``) and ``mapped`` (the mapping's points with a
        per-frame soft-limit flag, see :data:`series.LIMIT_KEYS`, and ``lips_clamped``).
    evenly : evenly spaced contact-sheet frames; thumb_height : contact-sheet height, px.
    title : the page's heading.
    sheet_threads : worker threads reading and encoding the contact-sheet frames (>= 1); the page
        does not depend on it.

    Returns
    -------
    The HTML document (str). Raises ValueError for inconsistent inputs.
    """
    if sheet_threads < 1:
        raise ValueError(f"sheet_threads must be >= 1, got {sheet_threads}")
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
    data["contact_sheet"] = sheet_frames(T, evenly=evenly, peaks=series.peak_frames(expression) if expression else [])
    data["head_pose"] = series.head_pose_series(pose)
    data["tracking"] = series.tracking_series(tracked)
    data["residuals"] = series.residual_series(pose, similarity)
    data["propagation"] = series.propagation_series(target)
    dominant = series.dominant_examples(coefficients)
    data["coefficients"] = {**dominant, "subregions": coefficients["subregions"], "examples": coefficients["examples"]}

    readers = ThreadPoolExecutor(max_workers=sheet_threads, thread_name_prefix="report-sheet")
    try:
        jpegs = [readers.submit(sheet_image, performer, result, frame, height=thumb_height)
                 for frame, _ in data["contact_sheet"]]
        from stages.report import sections  # matplotlib: imported while the sheet's frames are read

        if expression is not None:
            expression_body, data["follow"], poorly = sections.expression_section(
                expression, reference=reference, shaded=shaded, fps=fps)
            data["expression"] = expression
            warnings += poorly
        geometry_body = sections.geometry_section(data, shaded=shaded, fps=fps)
        coefficient_body = sections.coefficient_section(dominant, coefficients, limited=limited)
        sheet_body = contact_sheet(data["contact_sheet"], [jpeg.result() for jpeg in jpegs], fps=fps)
    finally:
        readers.shutdown(cancel_futures=True)

    warnings += frame_warnings(no_face=no_face, pose_valid=pose["valid"], limited=limited, mapped=mapped,
                               warp_only=bool((dominant["example"] < 0).all()))
    data["warnings"] = warnings
    parts = [
        Section("Warnings", listing(warnings, css="warn")),
        Section("Contact sheet: performer | result", sheet_body),
        Section("Expression: performer vs target (mouth opening, mouth width, brow raise)", expression_body),
        Section("Head pose, tracking and propagation", geometry_body),
        Section("Which example drives which subregion", coefficient_body),
        Section("Stage timings", not_available(TIMINGS_NOTE)),
    ]
    meta = (f"{T} frames at {fps:g} frames/s ({T / fps:.2f} s), performer {performer.info.width}x"
            f"{performer.info.height}, result {result.info.width}x{result.info.height}")
    return page(title=title, meta=meta, sections=parts, data=data)
