"""Stage registry: stages come from the entry-point group, like a third-party plugin's."""

from __future__ import annotations

import sys

import pytest

from runner.bundle import BundleType
from runner.registry import Registry, RegistryError, check_stage_class
from runner.stage import FrameStage, Param, SequenceStage
from stages.video import VideoDecode, WriteVideo
from tests.runner.helpers import ENTRY_POINTS, make_plugin_site


def _site(tmp_path, lines: dict[str, str], name: str = "plug"):
    info = tmp_path / f"{name}-0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 0\n")
    body = "\n".join(f"{k} = {v}" for k, v in lines.items())
    (info / "entry_points.txt").write_text(f"[expression_mapping.stages]\n{body}\n")


def test_entry_points_register_stages(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(make_plugin_site(tmp_path)))
    registry = Registry.from_entry_points()
    assert set(ENTRY_POINTS) <= set(registry.names())
    assert registry.get("video.decode") is VideoDecode and registry.get("write.video") is WriteVideo


def test_registry_rejects_conflicts_and_bad_targets(tmp_path, monkeypatch):
    _site(
        tmp_path / "a",
        {
            "video.decode": "stages.video:VideoDecode",
            "x.y": "stages.video:WriteVideo",
            "x.missing": "stages.video:Nope",
            "x.notstage": "stages.video:probe",
        },
    )
    monkeypatch.syspath_prepend(str(tmp_path / "a"))
    registry = Registry.from_entry_points()
    with pytest.raises(RegistryError, match="whose name is 'write.video'"):
        registry.get("x.y")
    with pytest.raises(RegistryError, match="cannot load stages.video:Nope"):
        registry.get("x.missing")
    with pytest.raises(RegistryError, match="not a Stage subclass"):
        registry.get("x.notstage")
    _site(tmp_path / "b", {"video.decode": "stages.video:ImageGray"}, name="other")
    monkeypatch.syspath_prepend(str(tmp_path / "b"))
    with pytest.raises(RegistryError, match="registered twice"):
        Registry.from_entry_points()


def test_stage_contract_checks():
    class NoVersion(SequenceStage):
        name = "a.b"

    class BadDefault(SequenceStage):
        name, version = "a.b", "1"
        params = (Param("n", int, "3", "count"),)

    class FramesFromSequence(SequenceStage):
        name, version = "a.b", "1"
        outputs = {"f": "frames"}

    class UncachedBundle(FrameStage):
        name, version, cached = "a.b", "1", False
        outputs = {"p": "points"}

    class NoShape(FrameStage):
        name, version = "a.b", "1"
        outputs = {"f": "frames"}

    class StringsInATuple(SequenceStage):
        name, version = "a.b", "1"
        inputs = {"p": ("points", "pose")}

    class BundleNamedAsARunnerType(SequenceStage):
        name, version = "a.b", "1"
        outputs = {"f": BundleType("files", "", ())}

    for cls, words in [
        (NoVersion, "'version'"),
        (BadDefault, "default of 'n'"),
        (NoShape, "define stream_info"),
        (FramesFromSequence, "only frame stages"),
        (UncachedBundle, "cached = False"),
        (StringsInATuple, "input 'p' must map a name to a type string, a BundleType or a tuple of them"),
        (BundleNamedAsARunnerType, "output 'f' must map a name to a type string or a BundleType"),
    ]:
        with pytest.raises(RegistryError, match=words):
            check_stage_class(cls)
    registry = Registry(classes=[VideoDecode])
    assert registry.names() == ["video.decode"] and "video.decode" in registry


def test_loading_a_pipeline_imports_only_the_stages_it_uses(tmp_path, monkeypatch):
    (tmp_path / "lazy_plugin_mod.py").write_text("raise ImportError('should not be imported')\n")
    _site(tmp_path, {"lazy.stage": "lazy_plugin_mod:Stage"})
    monkeypatch.syspath_prepend(str(tmp_path))
    registry = Registry.from_entry_points()
    assert "lazy.stage" in registry.names() and "lazy_plugin_mod" not in sys.modules
