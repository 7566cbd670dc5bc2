"""The drag image (editor/preview.py): size mapping, the reduced model, and the image against the pipeline's synthesis at full size (identical at scale 1,
its area-average at scale 1/2)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from editor.preview import PreviewSynthesizer, preview_size, reduced_model, to_preview
from stages.actor_pack import load_pack
from stages.synthesis.synthesize import Synthesizer
from tests.editor.conftest import PACK


@pytest.fixture(scope="module")
def model(pipeline):
    return pipeline[0]


@pytest.fixture(scope="module")
def synthesizer(model):
    return Synthesizer(model)


@pytest.fixture(scope="module")
def geometry():
    """A captured expression of the pack (its mouth and brows move)."""
    return load_pack(PACK).captured_points[3]


def test_preview_size_and_pixel_centres():
    assert preview_size((600, 800), 0.5) == (300, 400)
    assert preview_size((3, 5), 0.01) == (1, 1)
    with pytest.raises(ValueError, match="in \\(0, 1\\]"):
        preview_size((600, 800), 1.5)
    # The centre of full-size pixels 0 and 1 (x = 0.5) is the centre of half-size pixel 0; the
    # outer pixel edges (-0.5 and W - 0.5) stay the outer edges.
    np.testing.assert_allclose(to_preview([[0.5, 1.5], [-0.5, 7.5]], (4, 8), (2, 4)), [[0.0, 0.5], [-0.5, 3.5]])


def test_reduced_model_keeps_labels_and_averages_images(model):
    small = reduced_model(model, (60, 80))
    assert small["examples"].shape == model["examples"].shape[:1] + (80, 60, 3)
    assert small["blend_i1"].dtype == model["blend_i1"].dtype
    assert set(np.unique(small["blend_i1"])) <= set(np.unique(model["blend_i1"]))
    # A 4x reduction of the standard image is the mean of each 4x4 block.
    block = model["standard"].reshape(80, 4, 60, 4, 3).mean((1, 3))
    assert np.abs(small["standard"] - block).max() <= 0.5 + 1e-9
    np.testing.assert_array_equal(small["example_points"], model["example_points"])


def test_band_pass_blending_is_refused(model):
    with pytest.raises(ValueError, match="band-pass"):
        PreviewSynthesizer(Synthesizer(model, detail_power=2.0), model, scale=1.0)


def test_preview_at_scale_1_is_the_pipeline_synthesis(model, synthesizer, geometry):
    with torch.inference_mode():
        preview = PreviewSynthesizer(synthesizer, model, scale=1.0).render(geometry)
        full, _, _ = synthesizer.render(geometry[None])
    torch.testing.assert_close(preview, full, rtol=0, atol=1e-6)


def test_half_size_preview_is_the_area_average_of_the_full_synthesis(model, synthesizer, geometry):
    previewer = PreviewSynthesizer(synthesizer, model, scale=0.5)
    with torch.inference_mode():
        preview = previewer.render(geometry)[0].permute(1, 2, 0).numpy()
        full = synthesizer.render(geometry[None])[0][0].permute(1, 2, 0).numpy()
        neutral = previewer.render(load_pack(PACK).neutral.points)[0].permute(1, 2, 0).numpy()
    W, H = synthesizer.size
    assert preview.shape == (H // 2, W // 2, 3)
    expected = cv2.resize(full, (W // 2, H // 2), interpolation=cv2.INTER_AREA)
    error = np.abs(preview - expected)
    # Sampling the composite once per preview pixel instead of averaging four: close on average,
    # off at edges by part of the local contrast.
    assert error.mean() < 1.0 / 255 and np.percentile(error, 99) < 0.05
    # ...and it shows the expression, not the neutral.
    assert np.abs(neutral - expected).mean() > 3 * error.mean()
