"""Pipeline validation: each error kind reported with file, line, column and key; --set typing;
input binding."""

from __future__ import annotations

import os
import textwrap
from pathlib import Path

import pytest

from runner.config import ConfigError, bind_inputs, load_pipeline
from runner.registry import Registry
from runner.stage import FrameStage, Param, SequenceStage, StreamInfo


class Source(FrameStage):
    name = "t.source"
    version = "1"
    inputs = {"video": "video"}
    outputs = {"frames": "frames"}

    def stream_info(self, inputs, params):
        return StreamInfo(1, 25.0, 4, 4)


class Track(SequenceStage):
    name = "t.track"
    version = "1"
    inputs = {"frames": "frames", "pack": "dir"}
    optional_inputs = frozenset({"pack"})
    outputs = {"points": "points"}
    params = (
        Param("radius", int, 5, "search radius"),
        Param("sigma", float, 1.0, "smoothing"),
        Param("mode", str, "fast", "mode", choices=("fast", "exact")),
        Param("flip", bool, False, "mirror"),
        Param("ids", list, [], "point ids"),
    )


class Smooth(SequenceStage):
    name = "t.smooth"
    version = "1"
    inputs = {"points": "points"}
    outputs = {"points": "points"}


class Encode(SequenceStage):
    name = "t.encode"
    version = "1"
    inputs = {"points": "points"}
    params = (Param("crf", int, 18, "quality", min=0, max=51), Param("scale", float, 1.0, "factor", min=0.0))


REGISTRY = Registry(classes=[Source, Track, Smooth, Encode])


def load(tmp_path: Path, text: str, **kwargs):
    path = tmp_path / "p.yaml"
    path.write_text(textwrap.dedent(text).lstrip("\n"))
    return load_pipeline(path, REGISTRY, **kwargs)


def issues(tmp_path: Path, text: str, **kwargs) -> list[str]:
    with pytest.raises(ConfigError) as info:
        load(tmp_path, text, **kwargs)
    prefix = str(tmp_path / "p.yaml") + ":"
    return [str(i).removeprefix(prefix) for i in info.value.issues]


GOOD = """
inputs:
  clip: {type: video}
  pack: {type: dir, default: packs/a}
stages:
  src: {uses: t.source, inputs: {video: clip}}
  smooth:
    uses: t.smooth
    inputs: {points: track.points}
  track:
    uses: t.track
    params: {radius: 7, sigma: 2, ids: [1, 2]}
    inputs: {frames: src.frames, pack: pack}
"""


def test_valid_pipeline_resolves_order_defaults_and_paths(tmp_path):
    p = load(tmp_path, GOOD)
    assert list(p.stages) == ["src", "track", "smooth"]  # topological, file order among ties
    assert p.stages["track"].params == {"radius": 7, "sigma": 2.0, "mode": "fast", "flip": False, "ids": [1, 2]}
    assert isinstance(p.stages["track"].params["sigma"], float)
    assert p.inputs["pack"].default == tmp_path / "packs" / "a"
    assert p.chunk_frames == 16
    assert sorted(p.edges) == [("src", "track"), ("track", "smooth")]
    assert p.ancestors("smooth") == {"src", "track", "smooth"}


def test_unknown_stage(tmp_path):
    assert issues(tmp_path, "stages:\n  a: {uses: t.nope}\n") == [
        "2:13: stages.a.uses: unknown stage 't.nope' (see `runner stages`)"
    ]


def test_unknown_parameter_and_wrong_types_all_reported(tmp_path):
    found = issues(
        tmp_path,
        """
        inputs: {clip: {type: video}}
        stages:
          src: {uses: t.source, inputs: {video: clip}}
          track:
            uses: t.track
            params: {radius: "5", sigma: true, mode: slow, flip: 1, speed: 3}
            inputs: {frames: src.frames}
        """,
    )
    assert found == [
        "6:22: stages.track.params.radius: wrong type: expected int, got str '5'",
        "6:34: stages.track.params.sigma: wrong type: expected float, got bool True",
        "6:46: stages.track.params.mode: wrong value: expected one of 'fast', 'exact', got 'slow'",
        "6:58: stages.track.params.flip: wrong type: expected bool, got int 1",
        "6:61: stages.track.params.speed: unknown parameter of t.track (known: radius, sigma, mode, flip, ids)",
    ]


def test_missing_inputs(tmp_path):
    found = issues(
        tmp_path,
        """
        stages:
          src: {uses: t.source, inputs: {video: clip}}
          track: {uses: t.track, inputs: {frames: source.frames}}
          smooth: {uses: t.smooth}
          more: {uses: t.smooth, inputs: {points: src.points}}
        """,
    )
    assert found == [
        "2:41: stages.src.inputs.video: missing input: no pipeline input or stage output named 'clip'",
        "3:43: stages.track.inputs.frames: missing input: no stage named 'source'",
        "4:11: stages.smooth.inputs.points: missing input: t.smooth needs port 'points' (points)",
        "5:43: stages.more.inputs.points: missing input: src (t.source) has no output 'points' (outputs: frames)",
    ]


def test_port_type_mismatch(tmp_path):
    found = issues(
        tmp_path,
        """
        inputs: {clip: {type: video}, pack: {type: dir}}
        stages:
          src: {uses: t.source, inputs: {video: pack}}
          smooth: {uses: t.smooth, inputs: {points: src.frames}}
        """,
    )
    assert found == [
        "3:41: stages.src.inputs.video: port type mismatch: 'video' takes video, pack gives dir",
        "4:45: stages.smooth.inputs.points: port type mismatch: 'points' takes points, src.frames gives frames",
    ]


def test_cycle(tmp_path):
    found = issues(
        tmp_path,
        """
        stages:
          a: {uses: t.smooth, inputs: {points: c.points}}
          b: {uses: t.smooth, inputs: {points: a.points}}
          c: {uses: t.smooth, inputs: {points: b.points}}
        """,
    )
    assert len(found) == 1 and found[0].startswith("2:40: stages.a.inputs: cycle: a -> b -> c -> a")


def test_duplicate_names(tmp_path):
    """A key given twice is refused by the YAML reader (runner.safe_yaml) at the second one; a
    stage named like a pipeline input by the loader."""
    found = issues(
        tmp_path,
        """
        inputs: {clip: {type: video}}
        stages:
          src: {uses: t.source, inputs: {video: clip}}
          src: {uses: t.source, inputs: {video: clip}}
        """,
    )
    assert found == ["4:3: yaml: duplicate key 'src' (first at line 3, column 3)"]
    found = issues(
        tmp_path,
        """
        inputs: {clip: {type: video}}
        stages:
          clip: {uses: t.source, inputs: {video: clip}}
        """,
    )
    assert found == ["3:3: stages.clip: duplicate name: 'clip' is also a pipeline input"]


def test_unknown_keys_and_yaml_syntax(tmp_path):
    assert issues(tmp_path, "stage: {}\n") == [
        "1:1: stage: unknown key (expected one of: extends, chunk_frames, inputs, stages)",
        "1:1: stages: missing: a pipeline needs a `stages` mapping",
    ]
    assert issues(tmp_path, "stages: [\n")[0].startswith("2:1: yaml:")
    assert (
        issues(tmp_path, "chunk_frames: 0\nstages: {a: {uses: t.smooth, inputs: {points: a.points}}}\n")[0]
        == "1:15: chunk_frames: wrong type: expected a positive int, got 0"
    )


def test_set_overrides_are_typed_by_the_schema(tmp_path):
    p = load(
        tmp_path, GOOD, overrides=["track.radius=9", "track.sigma=0.5", "track.flip=yes", "track.ids=[3]", "track.mode=exact"]
    )
    assert p.stages["track"].params == {"radius": 9, "sigma": 0.5, "mode": "exact", "flip": True, "ids": [3]}
    found = issues(tmp_path, GOOD, overrides=["track.radius=big", "track.mode=slow", "nope.x=1", "track.zzz=1", "radius"])
    assert found == [
        "--set: track.radius: wrong type: expected int, got 'big'",
        "--set: track.mode: wrong value: expected one of 'fast', 'exact', got 'slow'",
        "--set: nope.x: unknown stage 'nope' in this pipeline",
        "--set: track.zzz: unknown parameter of t.track (known: radius, sigma, mode, flip, ids)",
        "--set: radius: expected --set stage.param=value",
    ]


def test_bind_inputs(tmp_path):
    p = load(tmp_path, GOOD)
    clip = tmp_path / "clip.mp4"
    clip.write_bytes(b"x")
    with pytest.raises(ConfigError) as info:
        bind_inputs(p, clip=None, named=[])
    assert [str(i).split(": ", 1)[1] for i in info.value.issues] == [
        "inputs.clip: missing input: no value given (use --in)",
        f"inputs.pack: missing input: {tmp_path / 'packs' / 'a'}: no such folder",
    ]
    (tmp_path / "packs" / "a").mkdir(parents=True)
    assert bind_inputs(p, clip=clip, named=[]) == {"clip": clip, "pack": tmp_path / "packs" / "a"}
    assert bind_inputs(p, clip=None, named=[f"clip={clip}", f"pack={tmp_path}"]) == {"clip": clip, "pack": tmp_path}
    with pytest.raises(ConfigError, match="unknown pipeline input"):
        bind_inputs(p, clip=clip, named=["other=x"])


def test_parameter_ranges_are_checked_when_the_graph_is_loaded(tmp_path):
    text = GOOD + "  enc: {uses: t.encode, params: {crf: 52, scale: -0.5}, inputs: {points: track.points}}\n"
    assert issues(tmp_path, text) == [
        "13:39: stages.enc.params.crf: out of range: expected 0 <= crf <= 51, got 52",
        "13:50: stages.enc.params.scale: out of range: expected 0.0 <= scale, got -0.5",
    ]
    good = GOOD + "  enc: {uses: t.encode, inputs: {points: track.points}}\n"
    assert issues(tmp_path, good, overrides=["enc.crf=100"]) == ["--set: enc.crf: out of range: expected 0 <= crf <= 51, got 100"]
    assert load(tmp_path, good, overrides=["enc.crf=0", "enc.scale=0"]).stages["enc"].params == {"crf": 0, "scale": 0.0}


def test_yaml_aliases_are_refused_with_their_position(tmp_path):
    bomb = (
        "a: &a [x, x, x, x, x, x, x, x, x]\n"
        + "".join(f"{b}: &{b} [{', '.join([f'*{a}'] * 9)}]\n" for a, b in zip("abcdefghi", "bcdefghij"))
        + "stages: {}\n"
    )
    assert issues(tmp_path, bomb) == ["2:8: yaml: alias *a is not allowed (aliases are refused)"]
    found = issues(tmp_path, "stages:\n  a: {uses: t.smooth, params: &p {}}\n  b: {uses: t.smooth, params: *p}\n")
    assert found == ["3:31: yaml: alias *p is not allowed (aliases are refused)"]


def test_python_tags_are_refused_with_their_position(tmp_path):
    found = issues(tmp_path, "stages:\n  a:\n    uses: !!python/object/apply:os.system ['true']\n")
    assert found == ["3:11: yaml: tag 'tag:yaml.org,2002:python/object/apply:os.system' is not allowed"]
    assert issues(tmp_path, GOOD, overrides=["track.ids=!!python/name:os.system"])[0].startswith("--set: track.ids: wrong type")


def write(folder: Path, name: str, text: str) -> Path:
    path = folder / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(textwrap.dedent(text).lstrip("\n"))
    return path


def test_extends_overlays_stages_params_and_wiring(tmp_path):
    write(tmp_path, "base/p.yaml", GOOD)
    child = write(
        tmp_path,
        "child.yaml",
        """
        extends: base/p.yaml
        chunk_frames: 8
        inputs:
          clip: {default: clips/c.mp4}
        stages:
          track:
            params: {radius: 9, ids: null}
            inputs: {pack: null}
          smooth: null
          encode: {uses: t.encode, inputs: {points: track.points}}
        """,
    )
    p = load_pipeline(child, REGISTRY)
    assert list(p.stages) == ["src", "track", "encode"]
    assert p.chunk_frames == 8
    assert p.stages["track"].params == {"radius": 9, "sigma": 2.0, "mode": "fast", "flip": False, "ids": []}
    assert {port: str(ref) for port, ref in p.stages["track"].inputs.items()} == {"frames": "src.frames"}
    assert (p.inputs["clip"].type, p.inputs["clip"].default) == ("video", tmp_path / "clips" / "c.mp4")
    assert p.inputs["pack"].default == tmp_path / "base" / "packs" / "a"  # relative to the file that wrote it
    assert p.stages["src"].where.file == str(tmp_path / "base" / "p.yaml")
    assert p.stages["track"].param_where["radius"].file == str(child)
    assert p.stages["track"].param_where["sigma"].file == str(tmp_path / "base" / "p.yaml")


def test_extends_errors_are_positioned_in_the_file_that_wrote_them(tmp_path):
    write(tmp_path, "base.yaml", "stages:\n  src: {uses: t.source, params: {crf: 3}, inputs: {video: clip}}\n")
    child = write(tmp_path, "child.yaml", "extends: base.yaml\ninputs: {clip: {type: video}}\nstages:\n  gone: null\n")
    with pytest.raises(ConfigError) as info:
        load_pipeline(child, REGISTRY)
    assert [str(i) for i in info.value.issues] == [
        f"{tmp_path / 'base.yaml'}:2:34: stages.src.params.crf: unknown parameter of t.source (known: none)",
        f"{child}:4:9: stages.gone: nothing to remove: {tmp_path / 'base.yaml'} has no stages.gone",
    ]


@pytest.mark.parametrize(
    ("files", "expected"),
    [
        (
            {"p.yaml": "extends: missing.yaml\n"},
            "p.yaml:1:10: extends: cannot read {tmp}/missing.yaml: No such file or directory",
        ),
        ({"p.yaml": "extends: [a]\n"}, "p.yaml:1:10: extends: wrong type: expected the path of a pipeline file, got ['a']"),
        (
            {"p.yaml": "extends: list.yaml\n", "list.yaml": "- a\n"},
            "p.yaml:1:10: extends: {tmp}/list.yaml is not a pipeline (expected a mapping)",
        ),
        (
            {"p.yaml": "extends: a.yaml\n", "a.yaml": "extends: p.yaml\n"},
            "a.yaml:1:10: extends: cycle of extends: {tmp}/p.yaml -> {tmp}/a.yaml -> {tmp}/p.yaml",
        ),
        (
            {"p.yaml": "extends: bad.yaml\n", "bad.yaml": "stages: [\n"},
            "bad.yaml:2:1: yaml: expected the node content, but found '<stream end>'",
        ),
    ],
)
def test_extends_problems_are_positioned(tmp_path, files, expected):
    for name, text in files.items():
        write(tmp_path, name, text)
    with pytest.raises(ConfigError) as info:
        load_pipeline(tmp_path / "p.yaml", REGISTRY)
    assert tmp_path == tmp_path.resolve()  # the cycle names resolved paths
    assert [str(i) for i in info.value.issues] == [f"{tmp_path}/{expected.format(tmp=tmp_path)}"]


@pytest.mark.parametrize("special", ["/dev/zero", "fifo"])
def test_a_pipeline_file_or_base_that_is_not_a_regular_file_is_refused_unread(tmp_path, special):
    """A pipeline file, or the base it extends, that is /dev/zero or a FIFO: one positioned
    line saying what it is, never read (reading /dev/zero never ends, a FIFO waits)."""
    target = Path(special)
    if special == "fifo":
        target = tmp_path / "fifo"
        os.mkfifo(target)
    kind = "a character device" if special == "/dev/zero" else "a FIFO (named pipe)"
    with pytest.raises(ConfigError) as info:
        load_pipeline(target, REGISTRY)
    assert [str(i) for i in info.value.issues] == [f"{target}: file: cannot read: {kind}, not a regular file"]
    (tmp_path / "base.yaml").symlink_to(target)
    found = issues(tmp_path, "extends: base.yaml\nstages: {}\n")
    assert found == [f"1:10: extends: cannot read {tmp_path / 'base.yaml'}: {kind}, not a regular file"]


def test_an_input_that_is_a_device_a_fifo_or_the_wrong_kind_says_what_it_is(tmp_path):
    os.mkfifo(tmp_path / "fifo")
    (tmp_path / "file").write_text("x")
    pipeline = load(tmp_path, GOOD)
    cases = {
        "/dev/zero": "wrong input: /dev/zero: a character device, not a regular file",
        str(tmp_path / "fifo"): f"wrong input: {tmp_path / 'fifo'}: a FIFO (named pipe), not a regular file",
        str(tmp_path / "nothing"): f"missing input: {tmp_path / 'nothing'}: no such file",
    }
    for clip, message in cases.items():
        with pytest.raises(ConfigError) as info:
            bind_inputs(pipeline, clip=Path(clip), named=[f"pack={tmp_path}"])
        assert [i.message for i in info.value.issues] == [message]
    with pytest.raises(ConfigError) as info:
        bind_inputs(pipeline, clip=tmp_path / "file", named=[f"pack={tmp_path / 'file'}"])
    assert [i.message for i in info.value.issues] == [f"wrong input: {tmp_path / 'file'}: a file, not a folder"]
