"""The writers through the real runner CLI: decode the tiny fixture clip, write EXRs and a
side-by-side preview video; check what the runner publishes."""

import os
import subprocess
import sys
from pathlib import Path

import av
import OpenImageIO as oiio
import pytest

from stages.video import probe

pytestmark = [pytest.mark.subprocess]

REPO = Path(__file__).resolve().parents[3]
TINY = REPO / "fixtures" / "clips" / "tiny.mp4"

ENTRY_POINTS = """[expression_mapping.stages]
video.decode = stages.video:VideoDecode
write.video = stages.video:WriteVideo
write.exr = stages.writers.exr:WriteExr
preview.side_by_side = stages.writers.preview:SideBySide
"""

PIPELINE = f"""chunk_frames: 16
inputs:
  clip: {{type: video, default: {TINY}, help: the clip}}
stages:
  decode: {{uses: video.decode, inputs: {{video: clip}}}}
  exr: {{uses: write.exr, params: {{threads: 2}}, inputs: {{frames: decode.frames}}}}
  side:
    uses: preview.side_by_side
    params: {{height: 64}}
    inputs: {{performer: decode.frames, result: decode.frames}}
  preview: {{uses: write.video, inputs: {{frames: side.frames}}}}
"""


def test_pipeline_publishes_exr_frames_and_preview(tmp_path: Path) -> None:
    info = tmp_path / "site" / "writers_test-0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: writers-test\nVersion: 0\n")
    (info / "entry_points.txt").write_text(ENTRY_POINTS)
    (tmp_path / "p.yaml").write_text(PIPELINE)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(info.parent), str(REPO)]),
        "RUNNER_CACHE_DIR": str(tmp_path / "cache"),
    }
    done = subprocess.run(
        [sys.executable, "-m", "runner.cli", "run", str(tmp_path / "p.yaml"), "--out", str(tmp_path / "out")],
        env=env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr

    clip = probe(TINY)
    exrs = sorted((tmp_path / "out" / "exr").glob("*.exr"))
    assert [p.name for p in exrs] == [f"frame.{i:06d}.exr" for i in range(clip.frames)]
    assert not list((tmp_path / "out" / "exr").glob(".*.part"))
    for i in (0, clip.frames - 1):
        spec = oiio.ImageInput.open(str(exrs[i])).spec()
        assert (spec.width, spec.height, spec.nchannels) == (clip.width, clip.height, 4)
        assert spec.getattribute("exmap:frame") == i
        assert spec.getattribute("exmap:time_s") == pytest.approx(i / clip.fps, rel=1e-6)

    videos = list((tmp_path / "out" / "preview").glob("*.mp4"))
    assert len(videos) == 1
    with av.open(str(videos[0])) as container:
        stream = container.streams.video[0]
        width = 2 * max(2, 2 * round(clip.width * 64 / clip.height / 2))
        assert (stream.width, stream.height) == (width, 64)
        assert sum(1 for _ in container.decode(video=0)) == clip.frames
