"""The bundle types' reference (scripts/bundles_page.py): every declared bundle type a stage names,
with its fields' dtype, shape, unit and meaning, the stages that produce and read it, and the
committed page is the one the declarations give."""

from __future__ import annotations

from runner.bundle import BundleType, Field
from runner.registry import Registry
from runner.stage import SequenceStage
from scripts import bundles_page

TRACK = BundleType(
    "track",
    "Points per frame.",
    (Field("xy", "f", ("T", "N", 2), "px", "positions"), Field("frame", "iu", (), "", "first | last", optional=True)),
)
OTHER = BundleType("other", "Something else.", ())


class Make(SequenceStage):
    name, version = "demo.make", "1"
    outputs = {"track": TRACK, "plain": "plain"}


class Read(SequenceStage):
    name, version = "demo.read", "1"
    inputs = {"track": (TRACK, OTHER), "plain": "plain"}


def test_a_declared_type_is_listed_with_its_fields_producers_and_readers():
    text = bundles_page.page(Registry(classes=[Make, Read]))
    assert "## `track`\n\nPoints per frame.\n\nFrom `demo.make`; read by `demo.read`." in text
    assert "| `xy` | float | `(T, N, 2)` | px | positions |" in text
    assert "| `frame` | int/uint | `()` |  | optional: first \\| last |" in text
    assert "## `other`\n\nSomething else.\n\nFrom no stage; read by `demo.read`.\n\nFields not declared" in text
    assert "`plain`" not in text  # an undeclared bundle has no entry


def test_the_committed_page_is_the_declarations():
    registry = Registry.from_entry_points()
    text = bundles_page.page(registry)
    for name in ("points", "pose_pnp", "pose_relative", "landmarks", "camera"):
        assert f"## `{name}`" in text
    assert "| `tvec` | float | `(T, 3)` | mm |" in text and "| `tvec` | float | `(T, 3)` | px |" in text
    assert bundles_page.main(["--check"]) == 0, "run python scripts/bundles_page.py"
