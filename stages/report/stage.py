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

from runner.stage import Context, Param, SequenceStage, StageError
from stages.writers.atomic import atomic_write
from stages.writers.bundles import check_bundle


class WriteReport(SequenceStage):
    """``write.report``: ``index.html`` under the ``report`` files output (see the module doc)."""

    name = "write.report"
    version = "2"
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
        Param("enabled", bool, True, "write the page; false turns the report off (out/<stage>/ then holds only "
              "its manifest, and nothing is read or drawn)"),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        if not params.get("enabled", True):
            return {"report": None}
        frames = inputs["performer"].info.frames
        if inputs["result"].info.frames != frames:
            raise StageError(f"{self.name}: input 'result' has {inputs['result'].info.frames} frames, "
                             f"'performer' has {frames}")
        for port, kind in (("target", "points"), ("tracked", "points"), ("pose", "pose"),
                           ("similarity", "similarity"), ("coefficients", "coefficients"), ("mapped", "points")):
            if inputs.get(port) is not None:
                check_bundle(inputs[port], stage=self.name, port=port, kind=kind, frames=frames)
        try:
            from stages.report.html import report_html  # matplotlib, OpenCV: only when run

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
