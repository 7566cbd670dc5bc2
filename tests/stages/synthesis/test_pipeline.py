"""synthesis.build -> synthesis.synthesize / synthesis.coefficients through the runner, chunk by chunk."""

import textwrap
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from runner.cache import CacheStore
from runner.config import bind_inputs, load_pipeline
from runner.execute import Options, Runner
from runner.registry import Registry
from runner.stage import Context, SequenceStage
from stages.actor_pack import load_pack
from stages.pack.stage import LoadPack
from stages.synthesis.build import BuildSynthesis
from stages.synthesis.coefficients import NameCoefficients
from stages.geometry.mapping import rms_radius
from stages.synthesis.coherence import coherent_coefficients
from stages.synthesis.synthesize import COHERENCE_FRAMES, COHERENCE_SIZE, Synthesize, Synthesizer
from tests.stages.synthesis.test_fixture_pack import PACK


class PackGeometry(SequenceStage):
    """Test source: the pack's examples' geometry, one per frame, as a ``points`` bundle."""

    name, version = "t.pack_points", "1"
    inputs = {"pack": "dir"}
    outputs = {"points": "points"}

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        pack = load_pack(inputs["pack"])
        xy = np.stack([e.points for e in pack.examples][:5])
        return {"points": {"xy": xy, "valid": np.ones(xy.shape[:2], bool), "fps": np.array(25.0)}}


class Gather(SequenceStage):
    """Test sink: the synthesized frames and masks of the whole clip as one bundle."""

    name, version = "t.gather", "1"
    inputs = {"frames": "frames", "mask": "frames"}
    outputs = {"all": "all"}

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        frames = np.concatenate([c for _, c in inputs["frames"].chunks()])
        mask = np.concatenate([c for _, c in inputs["mask"].chunks()])
        return {"all": {"frames": frames, "mask": mask, "fps": np.array(inputs["frames"].info.fps)}}


PIPELINE = """
chunk_frames: 2
inputs:
  target: {type: dir, default: PACK}
stages:
  pack: {uses: pack.load, inputs: {pack: target}}
  build: {uses: synthesis.build, inputs: {layout: pack.layout, images: pack.images}}
  geometry: {uses: t.pack_points, inputs: {pack: target}}
  synth: {uses: synthesis.synthesize, params: {coherence_frames: 0.0}, inputs: {model: build.model, points: geometry.points}}
  coherent: {uses: synthesis.synthesize, inputs: {model: build.model, points: geometry.points}}
  coeffs: {uses: synthesis.coefficients, inputs: {model: build.model, coeffs: synth.coeffs}}
  gather: {uses: t.gather, inputs: {frames: synth.frames, mask: synth.mask}}
"""


def test_runner_pipeline_matches_direct_synthesis(tmp_path: Path):
    path = tmp_path / "p.yaml"
    path.write_text(textwrap.dedent(PIPELINE).replace("PACK", str(PACK)))
    registry = Registry(classes=[LoadPack, BuildSynthesis, NameCoefficients, Synthesize, PackGeometry, Gather])
    pipeline = load_pipeline(path, registry)
    runner = Runner(pipeline, bind_inputs(pipeline, clip=None, named=[]), Options(cache=CacheStore(tmp_path / "cache")))
    runner.run()
    got = runner.values[("gather", "all")].get()
    model = runner.values[("build", "model")].get()
    pack = load_pack(PACK)
    rgb, alpha, coeffs = Synthesizer(model).render(np.stack([e.points for e in pack.examples][:5]))
    assert got["frames"].shape == (5, pack.image_size[1], pack.image_size[0], 3) and float(got["fps"]) == 25.0
    # The stage stores half floats: the direct result rounded to half, to the last bit.
    np.testing.assert_array_equal(got["frames"], rgb.permute(0, 2, 3, 1).half().numpy())
    np.testing.assert_array_equal(got["mask"], alpha.permute(0, 2, 3, 1).half().numpy())
    chunked = runner.values[("synth", "coeffs")].get()["coeffs"]
    np.testing.assert_allclose(chunked, coeffs.numpy(), atol=1e-12)
    table = runner.values[("coeffs", "coefficients")].get()
    assert table["coeff"].shape == (5, len(pack.layout.subregions), len(pack.examples) + len(pack.teeth_examples))
    np.testing.assert_array_equal(np.nan_to_num(table["coeff"])[:, :, : len(pack.examples)].sum(-1)[:, 0], chunked[:, 0].sum(-1))
    assert len(runner.entries["synth"]) == 3  # ceil(5 / 2) chunks
    # With the weights coherent in time (the default), chunk by chunk equals the whole clip at once.
    xy = np.stack([e.points for e in pack.examples][:5])
    synthesizer = Synthesizer(model)
    whole = coherent_coefficients(
        lambda p: synthesizer.coefficients(p).numpy(),
        xy,
        0,
        5,
        model["subregion_points"],
        sigma_frames=COHERENCE_FRAMES,
        sigma_px=COHERENCE_SIZE * rms_radius(np.asarray(model["neutral_points"])),
    )
    np.testing.assert_allclose(runner.values[("coherent", "coeffs")].get()["coeffs"], whole, atol=1e-12)
