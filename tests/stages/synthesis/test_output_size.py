"""synthesis.synthesize's output size is bounded by the memory a run takes: a width beyond the
parameter's range is refused when the pipeline is loaded, an output of more pixels than fit
before anything is synthesized, with its estimate."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from runner.config import ConfigError, load_pipeline
from runner.registry import Registry
from stages.synthesis.synthesize import MAX_OUTPUT_PIXELS, output_size, run_memory_gb, widest_output

REPO = Path(__file__).resolve().parents[3]
MODEL = {"size": np.array([240, 320])}  # the bundled target pack's images, W x H


def test_a_width_beyond_the_range_is_refused_at_load():
    with pytest.raises(ConfigError) as info:
        load_pipeline(REPO / "pipeline.yaml", Registry.from_entry_points(), overrides=["synthesize.width=4096"])
    assert str(info.value) == "--set: synthesize.width: out of range: expected 0 <= width <= 3840, got 4096"


def test_an_output_of_more_pixels_than_fit_is_refused_with_its_estimate():
    widest = widest_output((240, 320))
    (w, h), _ = output_size(MODEL, widest, upscale=True)
    assert w == widest and w * h <= MAX_OUTPUT_PIXELS and run_memory_gb((w, h)) <= 8.0
    with pytest.raises(ValueError) as info:
        output_size(MODEL, 3000, upscale=True)
    assert str(info.value) == (
        "a 3000x4000 output (12.0 MP) would take about 15.0 GB (1.2 GB per output megapixel); at most 6.2 MP "
        f"fit the 8 GB a run may take: width <= {widest} for the pack's 240x320 images"
    )
