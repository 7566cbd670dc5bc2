"""A frame stage that gives its frames another size (``test.half_size``, like ``render3d`` or
``preview.side_by_side``) reads the upstream chunks of its window only, so it streams in bounded
memory like any other; a stage whose frame count differs from its input's is refused."""

from __future__ import annotations

import pytest
import textwrap
from pathlib import Path

from tests.runner.helpers import REPO, read_log, run_cli, stage_status

pytestmark = [pytest.mark.subprocess]

# `add` is read by `half` (another size, cached, read by `write`) and by `mean` (a
# sequence stage reading the stream), as `texture` is by `render3d` and `usd` in pipeline_3d.yaml;
# 12 chunks, more than the chunks computed ahead of the slowest reader.
GRAPH = f"""
chunk_frames: 4
inputs:
  clip: {{type: video, default: {REPO / "fixtures" / "clips" / "tiny.mp4"}}}
stages:
  decode: {{uses: video.decode, inputs: {{video: clip}}}}
  add: {{uses: test.add, params: {{value: 10}}, inputs: {{frames: decode.frames}}}}
  half: {{uses: test.half_size, inputs: {{frames: add.frames}}}}
  write: {{uses: test.slow_write, params: {{crf: 20}}, inputs: {{frames: half.frames}}}}
  mean: {{uses: test.mean, inputs: {{frames: add.frames}}}}
"""


def test_resized_stream_of_many_chunks_streams_through(env, tmp_path: Path):
    graph, log = tmp_path / "graph.yaml", tmp_path / "log.jsonl"
    graph.write_text(textwrap.dedent(GRAPH))
    done = run_cli("run", graph, "--out", tmp_path / "out", "--log-json", log, env=env, cwd=tmp_path)  # hung before
    assert done.returncode == 0, done.stderr
    events = read_log(log)
    assert stage_status(events)["write"] == "ran" and (tmp_path / "out" / "write").is_dir()
    # Every chunk of add and half computed once, none again, and half's first chunk before add's
    # last: its key reads add's chunks of its window (it read the whole add stream before).
    order = [(e["stage"], e["start"]) for e in events if e.get("event") == "chunk" and e["stage"] in ("add", "half")]
    for stage in ("add", "half"):
        assert sorted(start for name, start in order if name == stage) == list(range(0, 48, 4))
    assert order.index(("half", 0)) < order.index(("add", 44))
    assert not [e for e in events if e.get("event") == "recompute"]


def test_cached_stage_after_an_uncached_resized_one_streams_through(env, tmp_path: Path):
    """A cached stage reading an uncached resized stream (`half` computed as read, then `more`):
    `more`'s first key needs `half`'s first chunk only; it hung when `half` keyed its chunks by
    whole input streams."""
    graph = tmp_path / "graph.yaml"
    graph.write_text(
        textwrap.dedent(GRAPH)
        .replace("uses: test.half_size,", "uses: test.half_size_on_demand,")
        .replace(
            "  write: {uses: test.slow_write, params: {crf: 20}, inputs: {frames: half.frames}}",
            "  more: {uses: test.add, params: {value: 1}, inputs: {frames: half.frames}}\n"
            "  write: {uses: test.slow_write, params: {crf: 20}, inputs: {frames: more.frames}}",
        )
    )
    done = run_cli("run", graph, "--out", tmp_path / "out", env=env, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "out" / "write").is_dir()


def test_stage_changing_the_frame_count_is_refused(env, tmp_path: Path):
    graph = tmp_path / "graph.yaml"
    graph.write_text(textwrap.dedent(GRAPH).replace("uses: test.half_size", "uses: test.every_other"))
    done = run_cli("run", graph, "--out", tmp_path / "out", env=env, cwd=tmp_path)
    assert done.returncode == 1
    assert "half" in done.stderr and "24 frames" in done.stderr and "48" in done.stderr and "Traceback" not in done.stderr
