"""The bundled pipelines written with ``extends:`` load to the pipeline their full text gave
(copies of those texts: ``data/*_full.yaml``)."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import pytest

from runner.config import Pipeline, load_pipeline
from runner.registry import Registry

REPO = Path(__file__).resolve().parents[2]
DATA = Path(__file__).parent / "data"


def what_runs(pipeline: Pipeline) -> dict[str, Any]:
    """Everything of a loaded pipeline a run's keys and outputs depend on, without the positions
    of the text. Not the order of ``stages`` (topological, ties in the file's order): a stage the
    child adds comes after the base's stages; the order decides when the runner visits a stage,
    not what the stage computes from its inputs and parameters."""
    folder = pipeline.path.parent
    return {
        "chunk_frames": pipeline.chunk_frames,
        "inputs": {n: (i.type, i.default and i.default.relative_to(folder), i.help) for n, i in pipeline.inputs.items()},
        "stages": {n: (s.uses, s.cls, s.params, {p: str(r) for p, r in s.inputs.items()}) for n, s in pipeline.stages.items()},
        "edges": sorted(pipeline.edges),
    }


@pytest.mark.parametrize("name", ["pipeline_3d.yaml", "pipeline_eigen.yaml", "pipeline_eigen_real.yaml"])
def test_an_extending_pipeline_loads_as_its_full_text(tmp_path, name):
    registry = Registry.from_entry_points()
    full = tmp_path / name
    shutil.copy(DATA / name.replace(".yaml", "_full.yaml"), full)  # beside nothing: it extends nothing
    assert "extends" not in full.read_text()
    assert what_runs(load_pipeline(REPO / name, registry)) == what_runs(load_pipeline(full, registry))
