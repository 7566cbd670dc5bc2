"""pack.load through the runner: each consumer's key covers what it reads of the pack.

Editing one example image re-runs ``synthesis.build`` (it reads the images) and leaves
``propagate.train`` and ``map.expression`` cached (they read the layout and the geometry); the
layout file's content is in every key that reads the layout, its comments are not.
"""

from __future__ import annotations

import re
import shutil
import textwrap
from pathlib import Path
from typing import Any, Mapping

import cv2
import numpy as np
import pytest

from runner.cache import CacheStore
from runner.config import bind_inputs, load_pipeline
from runner.execute import Options, Runner
from runner.registry import Registry
from runner.stage import Context, SequenceStage
from stages.actor_pack import load_pack
from stages.geometry.mapping import ExpressionMap
from stages.layout import LAYOUT_DIR
from stages.pack.bundles import pack_to_bundles
from stages.pack.stage import LoadPack
from stages.propagation.stage import TrainHierarchicalPCA
from stages.synthesis.build import BuildSynthesis
from tests.stages.test_actor_pack import _make_pack

pytestmark = [pytest.mark.slow]


class StillPerformer(SequenceStage):
    """Test source: three frames of zero displacement at every point of the pack's layout."""

    name, version = "t.still", "1"
    inputs = {"geometry": "pack_geometry"}
    outputs = {"displacements": "displacements"}

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        geometry = inputs["geometry"]
        n = len(geometry["names"])
        return {
            "displacements": {
                "d": np.zeros((3, n, 2)),
                "valid": np.ones((3, n), bool),
                "names": geometry["names"],
                "neutral": geometry["neutral"],
            }
        }


PIPELINE = """
inputs:
  target: {type: dir, default: PACK}
stages:
  pack: {uses: pack.load, inputs: {pack: target}}
  still: {uses: t.still, inputs: {geometry: pack.geometry}}
  map:
    uses: map.expression
    params: {mode: none}
    inputs: {displacements: still.displacements, layout: pack.layout, geometry: pack.geometry}
  train: {uses: propagate.train, inputs: {layout: pack.layout, geometry: pack.geometry}}
  build: {uses: synthesis.build, inputs: {layout: pack.layout, images: pack.images}}
"""


@pytest.fixture()
def run(tmp_path: Path):
    """A pack with its own copy of the layout, and a function running the pipeline on it that
    returns each stage's status."""
    root = tmp_path / "pack"
    _make_pack(root, np.random.default_rng(7))
    shutil.copy(LAYOUT_DIR / "zhang134.yaml", root / "layout.yaml")
    manifest = root / "pack.yaml"
    manifest.write_text(manifest.read_text().replace("layout: zhang134", "layout: layout.yaml"))
    path = tmp_path / "p.yaml"
    path.write_text(textwrap.dedent(PIPELINE).replace("PACK", str(root)))
    registry = Registry(classes=[LoadPack, StillPerformer, ExpressionMap, TrainHierarchicalPCA, BuildSynthesis])

    def statuses() -> dict[str, str]:
        pipeline = load_pipeline(path, registry)
        runner = Runner(pipeline, bind_inputs(pipeline, clip=None, named=[]), Options(cache=CacheStore(tmp_path / "cache")))
        return {r.stage: r.status for r in runner.run()}

    assert statuses() == dict.fromkeys(("pack", "still", "map", "train", "build"), "ran")
    return root, statuses


def test_outputs_are_the_packs_bundles(run, tmp_path: Path):
    root, _ = run
    pipeline = load_pipeline(
        tmp_path / "p.yaml", Registry(classes=[LoadPack, StillPerformer, ExpressionMap, TrainHierarchicalPCA, BuildSynthesis])
    )
    runner = Runner(pipeline, bind_inputs(pipeline, clip=None, named=[]), Options(cache=CacheStore(tmp_path / "cache")))
    runner.run()
    for port, want in pack_to_bundles(load_pack(root)).items():
        got = runner.values[("pack", port)].get()
        assert sorted(got) == sorted(want)
        for key in want:
            np.testing.assert_array_equal(got[key], want[key])


def test_an_example_image_reruns_build_only(run):
    root, statuses = run
    image = cv2.imread(str(root / "images" / "ex0.png"))
    image[0, 0] = 255 - image[0, 0]
    cv2.imwrite(str(root / "images" / "ex0.png"), image)
    assert statuses() == {"pack": "ran", "still": "cached", "map": "cached", "train": "cached", "build": "ran"}


def test_captured_geometry_reruns_map_and_train_not_build(run):
    root, statuses = run
    with np.load(root / "captured.npz") as z:
        captured = z["points"].copy()
    captured[0, 0] += 0.5
    np.savez(root / "captured.npz", points=captured)
    assert statuses() == {"pack": "ran", "still": "ran", "map": "ran", "train": "ran", "build": "cached"}


def test_layout_content_is_in_the_keys(run):
    root, statuses = run
    layout = root / "layout.yaml"
    layout.write_text("# a comment changes no key\n" + layout.read_text())
    assert statuses() == {"pack": "ran", "still": "cached", "map": "cached", "train": "cached", "build": "cached"}
    text = layout.read_text()
    name = re.search(r"^name: *(\S+)", text, re.M)
    layout.write_text(text[: name.start(1)] + "renamed" + text[name.end(1) :])
    assert statuses() == {"pack": "ran", "still": "cached", "map": "ran", "train": "ran", "build": "ran"}
