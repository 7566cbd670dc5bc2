"""``report.figures``: the timelines drawn ahead of ``write.report`` give the page it draws in one
go (byte for byte); a bundle drawn for another clip, or without a plot the page shows, is a stage
error naming the stage; the plots have one panel per series (their height in the fixed layout)."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from runner.stage import StageError
from stages.geometry.signals import SIGNALS
from stages.layout import load_layout
from stages.report import figures as layout
from stages.report.stage import WriteReport
from tests.memory_stream import files_context
from tests.stages.report.synthetic import FPS
from tests.stages.report.test_stage import PARAMS, figures, sheet, stage_inputs, write


def variants():
    """Synthetic runs: all points; the paper's tracked subset with a recorded neutral frame and no
    mapping; a warp-only run whose tracked points have no brows (no expression timeline)."""
    yield stage_inputs()
    layout134 = load_layout("zhang134")
    subset = stage_inputs(tracked_names=tuple(layout134.point_names[i] for i in layout134.tracked), with_mapped=False)
    subset["displacements"] = {"neutral_frame": np.array(10)}
    yield subset
    browless = stage_inputs()
    browless["coefficients"]["coeff"] = np.where(np.isnan(browless["coefficients"]["coeff"]), np.nan, 0.0)
    keep = np.array([not str(n).startswith("brow") for n in browless["tracked"]["names"]])
    browless["tracked"] = {k: (v[:, keep] if k != "names" else v[keep]) for k, v in browless["tracked"].items()}
    yield browless


@pytest.mark.parametrize("index", range(3))
def test_page_with_timelines_drawn_ahead_is_the_page_drawn_in_one_go(tmp_path: Path, index: int):
    inputs = list(variants())[index]
    ahead = write(inputs, tmp_path / "ahead").read_bytes()
    assert write(inputs, tmp_path / "one_go", ahead=False).read_bytes() == ahead


def png_height(data: np.ndarray) -> int:
    image = cv2.imdecode(np.asarray(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image is not None and image.shape[1] == int(layout.WIDTH_IN * layout.DPI)
    return image.shape[0]


def timeline_height(panels: int) -> int:
    """Pixel height of a timeline of ``panels`` rows in the fixed layout of ``figures.fixed_figure``."""
    inches = layout.TOP_IN + layout.BOTTOM_IN + panels * layout.PANEL_IN + (panels - 1) * layout.GAP_IN
    return int(inches * layout.DPI)  # Agg truncates the canvas size


def test_bundle_holds_one_panel_per_series():
    inputs = stage_inputs()
    bundle = figures(inputs)
    assert int(bundle["frames"]) == len(inputs["tracked"]["xy"]) and float(bundle["fps"]) == FPS
    assert png_height(bundle["expression"]) == timeline_height(len(SIGNALS))
    # head pose, tracking, residuals, and the propagation's iterations and input error
    assert png_height(bundle["geometry"]) == timeline_height(5)
    without = {k: v for k, v in inputs["target"].items() if k not in ("iterations", "input_error_px")}
    assert png_height(figures({**inputs, "target": without})["geometry"]) == timeline_height(3)
    assert "expression" not in figures(list(variants())[2])


def test_the_rate_is_the_points_else_the_parameter():
    """A tracker records the clip's rate in its points; the parameter stands in where none does,
    and a rate that is not the clip's is refused by the page."""
    inputs = stage_inputs()
    assert float(figures({**inputs, "tracked": {**inputs["tracked"], "fps": np.array(12.5)}})["fps"]) == 12.5
    bundle = figures(inputs, fps=30.0)
    bundles = {port: value for port, value in inputs.items() if port not in ("performer", "result")}
    with pytest.raises(StageError, match=r"write.report: figures: drawn for 40 frames at 30 frames/s, the contact "
                                         r"sheet has 40 frames at 25 frames/s"):
        WriteReport().run({**bundles, "figures": bundle, "sheet": sheet(inputs)}, PARAMS, files_context(Path("/x")))


def test_a_missing_plot_or_bad_input_is_a_stage_error(tmp_path: Path):
    inputs = stage_inputs()
    bundles = {port: value for port, value in inputs.items() if port not in ("performer", "result")}
    no_expression = figures(list(variants())[2])
    with pytest.raises(StageError, match="write.report: figures: no expression plot, which this page shows"):
        WriteReport().run({**bundles, "figures": no_expression, "sheet": sheet(inputs)}, PARAMS,
                          files_context(tmp_path))
    assert not (tmp_path / "report").exists()
    inputs["similarity"] = {**inputs["similarity"], "residual_px": inputs["similarity"]["residual_px"][:-1]}
    with pytest.raises(StageError, match="report.figures: input 'similarity' field 'residual_px'"):
        figures(inputs)
