"""The stage reference (scripts/stages_page.py): every registered stage with its ports and every
parameter's default and range as the stage class declares them, and the committed page is the
one the registry gives."""

from __future__ import annotations

from runner.registry import Registry
from runner.stage import Param, SequenceStage
from scripts import stages_page


class Blur(SequenceStage):
    name = "demo.blur"
    version = "3"
    doc = "Blurs a bundle."
    inputs = {"points": "points", "mask": "mask"}
    optional_inputs = frozenset({"mask"})
    outputs = {"points": "points"}
    params = (
        Param("sigma", float, 1.5, "Gaussian sigma | frames", min=0.0, max=10.0),
        Param("mode", str, "reflect", "ends", choices=("reflect", "hold")),
    )


def test_a_stage_is_listed_with_its_ports_and_its_parameters_defaults_and_ranges():
    text = stages_page.page(Registry(classes=[Blur]))
    assert "## demo" in text and "### `demo.blur`" in text and "Blurs a bundle." in text
    assert "Version 3, sequence stage; in no bundled pipeline." in text
    assert "| in | `mask` | mask, optional |" in text and "| out | `points` | points |" in text
    assert "| `sigma` | float | `1.5` | 0.0 ≤ value ≤ 10.0 | Gaussian sigma \\| frames |" in text
    assert "| `mode` | str | `'reflect'` | one of `'reflect'`, `'hold'` | ends |" in text


def test_the_committed_page_is_the_registrys():
    registry = Registry.from_entry_points()
    text = stages_page.page(registry)
    for name in registry.names():
        assert f"### `{name}`" in text
        for p in registry.get(name).params:
            assert f"| `{p.name}` |" in text
    assert "in `pipeline.yaml`" in text  # the bundled pipelines that use a stage are named
    assert stages_page.main(["--check"]) == 0, "run python scripts/stages_page.py"
