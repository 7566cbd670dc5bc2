"""``write.report``: one self-contained HTML page to judge a run (``<out>/<stage>/index.html``), and
``report.sheet``: its contact sheet, picked from the frame streams while they are computed.

The page shows a contact sheet (performer | result at evenly spaced frames and at the expression
peaks), performer vs target expression signals, head pose, tracking validity and fit residuals,
the motion propagation's iterations and residual (Sec. 10.1), which example drives which
subregion (the coefficients of eq. 2-5), the frames whose geometry left the target pack's range,
the face regions an occluder hid, and the run's warnings. Everything comes from the run's own data and is drawn deterministically,
so a cached run's report is byte-identical and costs only its own (cheap) recomputation.

The contact sheet is a stage of its own because its frames are known from the geometry alone:
``report.sheet`` reads no synthesis output but the frames, so the runner runs it while the
result is synthesized and hands it the chosen frames as they pass (nothing synthesized twice);
``write.report`` needs the whole run's coefficients, so it runs after the synthesis, from bundles.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from runner.stage import Context, Param, SequenceStage, StageError
from stages.geometry.bundles import DISPLACEMENTS, HEAD_POSES, POINTS, SIMILARITY
from stages.occlusion.bundles import OCCLUSION
from stages.report.bundles import SHEET
from stages.synthesis.bundles import COEFFICIENTS
from stages.writers.atomic import atomic_write
from stages.writers.bundles import check_bundle


def check_bundles(stage: str, inputs: Mapping[str, Any], kinds: Mapping[str, str], frames: int) -> None:
    """:func:`stages.writers.bundles.check_bundle` for each of ``kinds`` (port -> type) present."""
    for port, kind in kinds.items():
        if inputs.get(port) is not None:
            check_bundle(inputs[port], stage=stage, port=port, kind=kind, frames=frames)


class ContactSheet(SequenceStage):
    """``report.sheet``: performer | result JPEGs at the contact sheet's frames (see the module doc)."""

    name = "report.sheet"
    version = "2"
    doc = "the report's contact sheet: performer | result JPEGs at evenly spaced frames and the expression peaks"
    inputs = {
        "performer": "frames",
        "result": "frames",
        "target": POINTS,
        "tracked": POINTS,
        "pose": HEAD_POSES,
        "displacements": DISPLACEMENTS,
    }
    optional_inputs = frozenset({"displacements"})
    outputs = {"sheet": SHEET}
    params = (
        Param("sheet_frames", int, 8, "evenly spaced contact-sheet frames (the expression peaks are added)", min=0, max=200),
        Param("thumb_height", int, 180, "contact-sheet image height, px", min=16, max=2160),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        performer, result = inputs["performer"], inputs["result"]
        frames = performer.info.frames
        if result.info.frames != frames:
            raise StageError(f"{self.name}: input 'result' has {result.info.frames} frames, 'performer' has {frames}")
        check_bundles(self.name, inputs, {"target": "points", "tracked": "points", "pose": "pose"}, frames)
        from stages.report import series, sheet  # OpenCV, SciPy: only when run

        reference = series.reference_frame(inputs.get("displacements"), inputs["pose"])
        try:
            chosen = sheet.chosen_frames(
                inputs["tracked"], inputs["target"], reference=reference or 0, frames=frames, evenly=int(params["sheet_frames"])
            )
            jpegs = []
            for f, _ in chosen:  # ascending: a stream being computed hands each frame over as it passes
                jpegs.append(
                    sheet.sheet_jpeg(performer.read(f, f + 1)[0], result.read(f, f + 1)[0], height=int(params["thumb_height"]))
                )
                ctx.progress(1)
        except (KeyError, ValueError) as exc:
            raise StageError(f"{self.name}: {exc}") from None
        sizes = [(s.info.width, s.info.height) for s in (performer, result)]
        return {
            "sheet": sheet.sheet_bundle(
                chosen, jpegs, frames=frames, fps=float(performer.info.fps), performer_size=sizes[0], result_size=sizes[1]
            )
        }


class WriteReport(SequenceStage):
    """``write.report``: ``index.html`` under the ``report`` files output (see the module doc)."""

    name = "write.report"
    version = "5"
    doc = "an HTML page to judge the run: contact sheet, expression/pose/tracking curves, coefficients, warnings"
    inputs = {
        "sheet": SHEET,
        "target": POINTS,
        "tracked": POINTS,
        "pose": HEAD_POSES,
        "similarity": SIMILARITY,
        "coefficients": COEFFICIENTS,
        "displacements": DISPLACEMENTS,
        "mapped": POINTS,
        "occlusion": OCCLUSION,
    }
    optional_inputs = frozenset({"displacements", "mapped", "occlusion"})
    outputs = {"report": "files"}
    imports = ("stages.report.sections",)  # matplotlib (~1 s of one core): imported while the frames stream
    params = (
        Param("title", str, "Expression mapping: run report", "the page's heading"),
        Param(
            "enabled",
            bool,
            True,
            "write the page; false turns the report off (out/<stage>/ then holds only "
            "its manifest, and nothing is read or drawn)",
        ),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        if not params.get("enabled", True):
            return {"report": None}
        frames = int(inputs["sheet"]["frames"])
        check_bundles(
            self.name,
            inputs,
            {
                "target": "points",
                "tracked": "points",
                "pose": "pose",
                "similarity": "similarity",
                "coefficients": "coefficients",
                "mapped": "points",
                "occlusion": "occlusion",
            },
            frames,
        )
        try:
            from stages.report.html import report_html  # matplotlib: only when run

            text = report_html(inputs, title=str(params["title"]))
        except (KeyError, ValueError) as exc:
            raise StageError(f"{self.name}: {exc}") from None
        folder = Path(ctx.files_dir("report"))
        folder.mkdir(parents=True, exist_ok=True)
        with atomic_write(folder / "index.html") as tmp:
            Path(tmp).write_text(text, encoding="utf-8")
        ctx.progress(frames)
        return {"report": None}
