"""The report page of ``write.report`` built from a run's bundles (see :mod:`stages.report.stage`).
Kept apart from the stage's declaration so that loading a pipeline does not import matplotlib.

The contact sheet comes ready-made in the ``sheet`` bundle of ``report.sheet``
(:mod:`stages.report.sheet`), which picks its frames from the streams while they are computed.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from stages.report import series
from stages.report.page import Section, image, listing, not_available, page
from stages.report.sheet import sheet_images

SPANS_SHOWN = 12
TIMINGS_NOTE = (
    "the runner does not hand stage timings to stages (and timings would make the page differ "
    "between runs); `runner run --log-json FILE` records them"
)


def frame_list(flags: np.ndarray) -> str:
    """``"3-7, 12, 40-41"``: the frames where ``flags`` is True, as ranges (the first few)."""
    runs = series.spans(flags)
    text = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in runs[:SPANS_SHOWN])
    return text + (f", ... ({len(runs) - SPANS_SHOWN} more ranges)" if len(runs) > SPANS_SHOWN else "")


def frame_warnings(
    *,
    no_face: np.ndarray,
    pose_valid: np.ndarray,
    limited: np.ndarray | None,
    mapped: Mapping[str, np.ndarray] | None,
    warp_only: bool,
) -> list[str]:
    """One line per problem of the run's frames (plain text).

    Parameters
    ----------
    no_face, pose_valid : (T,) bool.
    limited : (T,) bool or None, frames soft-limited to the pack's range.
    mapped : the mapping's bundle or None (its ``lips_clamped (T,)`` is read when present).
    warp_only : every synthesis coefficient is zero.
    """
    T = len(no_face)
    flagged = [
        ("No face in {n} of {T} frames: {f}", no_face),
        ("No valid head pose in {n} frames with a face: {f}", ~np.asarray(pose_valid, bool) & ~no_face),
    ]
    if limited is not None:
        flagged.append(("Geometry soft-limited to the target pack's range in {n} of {T} frames: {f}", limited))
    if mapped is not None and "lips_clamped" in mapped:
        flagged.append(("Inner lips kept apart in {n} of {T} frames: {f}", np.asarray(mapped["lips_clamped"], bool)))
    lines = [text.format(n=int(flags.sum()), T=T, f=frame_list(flags)) for text, flags in flagged if flags.any()]
    if warp_only:
        lines.append("No synthesis coefficients: every subregion is zero in every frame (warp-only run)")
    return lines


def contact_sheet(images: Sequence[tuple[int, str, bytes]], *, fps: float) -> str:
    """The contact sheet's HTML: one captioned image per ``(frame, label, performer | result
    JPEG)`` of ``images`` (:func:`stages.report.sheet.sheet_images`)."""
    figures = "".join(
        f"<figure>{image(jpeg, 'image/jpeg', f'frame {f}', css='')}"
        f"<figcaption>frame {f} ({f / fps:.2f} s){': ' + label if label else ''}</figcaption></figure>"
        for f, label, jpeg in images
    )
    return f'<div class="sheet">{figures}</div>' if figures else not_available("no frame chosen")


def report_html(inputs: Mapping[str, Any], *, title: str) -> str:
    """The report page of one run.

    Parameters
    ----------
    inputs : the stage's inputs: the contact ``sheet`` bundle (:mod:`stages.report.sheet`, which
        also gives the frame count, rate and sizes); bundles ``target``, ``tracked`` (points),
        ``pose``, ``similarity``, ``coefficients``; optional ``displacements`` (its
        ``neutral_frame``) and ``mapped`` (the mapping's points with a per-frame soft-limit
        flag, see :data:`series.LIMIT_KEYS`, and ``lips_clamped``), ``occlusion`` (the occluded
        face regions of ``occlusion.detect``).
    title : the page's heading.

    Returns
    -------
    The HTML document (str). Raises ValueError for inconsistent inputs.
    """
    sheet = inputs["sheet"]
    T, fps = int(sheet["frames"]), float(sheet["fps"])
    tracked, target, pose, similarity = inputs["tracked"], inputs["target"], inputs["pose"], inputs["similarity"]
    mapped, coefficients = inputs.get("mapped"), inputs["coefficients"]
    chosen = series.reference_frame(inputs.get("displacements"), pose)
    reference = 0 if chosen is None else chosen
    no_face = ~series.frame_valid(tracked)
    limited = series.limited_frames(mapped)
    shaded = {"no face": series.spans(no_face), "limited": [] if limited is None else series.spans(limited)}
    displacements = inputs.get("displacements") or {}
    if bool(np.asarray(displacements.get("neutral_estimated", False))):
        warnings = [
            f"Reference (neutral): estimated from the clip, region by region; the nearest single frame, "
            f"{reference}, is in the contact sheet and the curves are read from it"
        ]
    else:
        warnings = [
            f"Reference (neutral) frame: {reference}"
            + (" (recorded by the run)" if chosen is not None else " (the run records none; the pipeline takes the first frame)")
        ]
    data: dict[str, Any] = {"frames": T, "fps": fps, "reference_frame": reference, "no_face": no_face, "limited": limited}

    try:
        expression = series.expression_series(tracked, target, reference=reference)
    except ValueError as exc:
        expression, expression_body = None, not_available(str(exc))
    images = sheet_images(sheet)
    data["contact_sheet"] = [(f, label) for f, label, _ in images]
    data["head_pose"] = series.head_pose_series(pose)
    data["tracking"] = series.tracking_series(tracked)
    data["residuals"] = series.residual_series(pose, similarity)
    data["propagation"] = series.propagation_series(target)
    dominant = series.dominant_examples(coefficients)
    data["coefficients"] = {**dominant, "subregions": coefficients["subregions"], "examples": coefficients["examples"]}

    from stages.report import sections  # matplotlib: only when a page is drawn

    if expression is not None:
        expression_body, data["follow"], poorly = sections.expression_section(
            expression, reference=reference, shaded=shaded, fps=fps
        )
        data["expression"] = expression
        warnings += poorly
    try:
        states = series.state_series(tracked, target)
        states_body, beyond = sections.states_section(states, mapped, shaded=shaded, fps=fps, frame_list=frame_list)
        data["states"] = states
        warnings += beyond
    except ValueError as exc:
        states_body = not_available(str(exc))
    geometry_body = sections.geometry_section(data, shaded=shaded, fps=fps)
    coefficient_body = sections.coefficient_section(dominant, coefficients, limited=limited)
    occlusion = inputs.get("occlusion")
    if occlusion is None:
        occlusion_body = not_available("the run detects no occlusion (connect occlusion.detect to 'occlusion')")
    else:
        regions = [str(r) for r in occlusion["regions"]]
        hidden = np.asarray(occlusion["occluded"], bool)
        ranges = {r: frame_list(hidden[:, k]) for k, r in enumerate(regions)}
        occlusion_body = sections.occlusion_section(occlusion, ranges)
        data["occlusion"] = {r: hidden[:, k] for k, r in enumerate(regions)}
        if hidden.any():
            warnings.append(
                "Occluded face regions: "
                + "; ".join(
                    f"{r} in {int(hidden[:, k].sum())} of {T} frames ({ranges[r]})"
                    for k, r in enumerate(regions)
                    if hidden[:, k].any()
                )
            )
    sheet_body = contact_sheet(images, fps=fps)

    warnings += frame_warnings(
        no_face=no_face, pose_valid=pose["valid"], limited=limited, mapped=mapped, warp_only=bool((dominant["example"] < 0).all())
    )
    data["warnings"] = warnings
    parts = [
        Section("Warnings", listing(warnings, css="warn")),
        Section("Contact sheet: performer | result", sheet_body),
        Section("Expression: performer vs target (mouth opening, mouth width, brow raise)", expression_body),
        Section("States: eyes, lip seal, and what the pack cannot show", states_body),
        Section("Head pose, tracking and propagation", geometry_body),
        Section("Which example drives which subregion", coefficient_body),
        Section("Occlusion: face regions hidden by a hand or an object", occlusion_body),
        Section("Stage timings", not_available(TIMINGS_NOTE)),
    ]
    (pw, ph), (rw, rh) = (tuple(int(v) for v in sheet[k]) for k in ("performer_size", "result_size"))
    meta = f"{T} frames at {fps:g} frames/s ({T / fps:.2f} s), performer {pw}x{ph}, result {rw}x{rh}"
    return page(title=title, meta=meta, sections=parts, data=data)
