"""Every numeric parameter of every registered stage has a closed range, so that a value that
would allocate without bound (a 20000x20000 pack image, a kernel 1e308 wide) is refused when
the graph is loaded, exit 2, before anything runs."""

from __future__ import annotations

import numpy as np
import pytest

from runner.config import ConfigError, load_pipeline
from runner.registry import Registry
from runner.stage import StageError
from stages.geometry.smooth import one_euro_smooth
from stages.geometry.subset import param_columns
from tests.runner.helpers import REPO, run_cli

REGISTRY = Registry.from_entry_points()


def numeric_params():
    for name in REGISTRY.names():
        for param in REGISTRY.get(name).params:
            if param.type in (int, float) and not param.choices:
                yield name, param


def test_every_numeric_parameter_has_a_minimum_and_a_maximum():
    params = list(numeric_params())
    assert len(params) > 80  # the registry was read
    unbounded = [f"{stage}.{p.name}" for stage, p in params if p.min is None or p.max is None]
    assert unbounded == []
    assert all(p.min <= p.default <= p.max for _, p in params)


@pytest.mark.parametrize(
    "pipeline, override, message",
    [
        ("pack_build.yaml", "select.width=20000", "out of range: expected 32 <= width <= 4096, got 20000"),
        ("pack_build.yaml", "select.captured=1000000", "out of range: expected 2 <= captured <= 256, got 1000000"),
        ("pipeline.yaml", "smooth.beta=1e308", "out of range: expected 0.0 <= beta <= 1000.0, got 1e+308"),
        ("pipeline_paper.yaml", "smooth.truncate=1e308", "out of range: expected 0.0 <= truncate <= 20.0, got 1e+308"),
        ("pipeline.yaml", "compensate.neutral_frame=-5", "out of range: expected -1 <= neutral_frame <= 10000000, got -5"),
        # 0, which the stages refuse, is outside the declared range
        ("pipeline.yaml", "smooth.min_cutoff=0", "out of range: expected 0.001 <= min_cutoff <= 1000.0, got 0.0"),
        ("pipeline.yaml", "smooth.d_cutoff=0", "out of range: expected 0.001 <= d_cutoff <= 1000.0, got 0.0"),
        ("pipeline.yaml", "train.variance_kept=0", "out of range: expected 0.01 <= variance_kept <= 1.0, got 0.0"),
        # list items: their declared type, each given once
        ("pipeline.yaml", "compensate.rigid_points=[[a]]", "wrong type: expected a list of str, got item 0 ['a']"),
        ("pipeline.yaml", "compensate.rigid_points=[{a: 1}]", "wrong type: expected a list of str, got item 0 {'a': 1}"),
        ("pipeline.yaml", "compensate.rigid_points=[eye_l_0, 3]", "wrong type: expected a list of str, got item 1 3"),
        ("pipeline.yaml", "compensate.rigid_points=[eye_l_0, eye_l_0, eye_l_0]", "wrong value: 'eye_l_0' is given twice"),
        ("pipeline.yaml", "points.layout=/dev/zero", "wrong value: '/dev/zero': a character device, not a regular file"),
    ],
)
def test_a_value_outside_what_a_parameter_declares_is_refused_before_anything_runs(pipeline, override, message):
    with pytest.raises(ConfigError) as info:
        load_pipeline(REPO / pipeline, REGISTRY, overrides=[override])
    assert [str(issue) for issue in info.value.issues] == [f"--set: {override.split('=')[0]}: {message}"]


def test_the_smallest_declared_values_are_accepted_by_the_stages():
    values = np.random.default_rng(0).normal(size=(5, 2, 2))
    smooth, _ = one_euro_smooth(values, np.ones((5, 2), bool), fps=25.0, min_cutoff=0.001, beta=0.0, d_cutoff=0.001)
    assert np.isfinite(smooth).all()


def test_every_list_parameter_declares_its_item_type():
    lists = [(stage, p) for stage in REGISTRY.names() for p in REGISTRY.get(stage).params if p.type is list]
    assert len(lists) >= 2 and [f"{stage}.{p.name}" for stage, p in lists if p.items is None] == []


def test_a_point_name_the_layout_does_not_have_fails_naming_the_parameter():
    names = np.array(["eye_l_0", "eye_r_0", "nose_tip"])
    assert param_columns(names, ["nose_tip", "eye_l_0"], stage="compensate", param="rigid_points").tolist() == [2, 0]
    with pytest.raises(StageError) as info:
        param_columns(names, ["eye_l_0", "nose"], stage="compensate", param="rigid_points")
    assert str(info.value) == "compensate: parameter rigid_points names ['nose'] that are not tracked points of the layout"


@pytest.mark.subprocess
def test_the_command_exits_2_on_select_width_20000(tmp_path, env):
    done = run_cli(
        "run",
        REPO / "pack_build.yaml",
        "--set",
        "select.width=20000",
        "--set",
        "select.height=20000",
        "--dry-run",
        env=env,
        cwd=tmp_path,
    )
    assert done.returncode == 2 and "select.width: out of range" in done.stderr and "select.height" in done.stderr
