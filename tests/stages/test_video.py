"""Video decode/encode against synthetic ground truth (FFV1 is lossless, so decoded frames must equal
the written ones exactly), and one-line errors for bad input."""

from __future__ import annotations

import threading
from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import pytest

from runner.stage import Context, StageError, StreamInfo
from runner.streams import chunk_ranges
from scripts.make_test_clip import synthetic_frames, write_clip
from tests.memory_stream import NpyStream
from tests.runner.helpers import REPO
from stages.color import luma_opencv
from stages.video import ImageGray, VideoDecode, VideoWriter, WriteVideo, probe


def _decode_all(path: Path) -> np.ndarray:
    with av.open(str(path)) as container:
        return np.stack([f.to_ndarray(format="rgb24") for f in container.decode(video=0)])


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return 10 * np.log10(255.0**2 / mse)


@pytest.fixture(scope="module")
def lossless(tmp_path_factory) -> tuple[Path, np.ndarray]:
    path = tmp_path_factory.mktemp("video") / "clip.mkv"
    write_clip(path, frames=37, width=64, height=48, fps=30000 / 1001, codec="ffv1")
    return path, synthetic_frames(0, 37, width=64, height=48)


def test_decode_is_exact_on_lossless_clip_in_any_chunk_order(lossless):
    path, truth = lossless
    stage = VideoDecode()
    info = stage.stream_info({"video": path}, {})
    assert info == StreamInfo(frames=37, fps=pytest.approx(29.97003), width=64, height=48)
    for start, stop in [(0, 16), (16, 32), (32, 37), (5, 9), (0, 3), (30, 37)]:
        frames = stage.process(start, stop, {"video": path}, {}, None)["frames"]
        assert frames.dtype == np.uint8 and frames.shape == (stop - start, 48, 64, 3)
        np.testing.assert_array_equal(frames, truth[start:stop])
    with pytest.raises(StageError, match="truncated stream: frame 37 missing"):
        stage.process(30, 40, {"video": path}, {}, None)


def test_decode_from_several_threads_at_once_is_exact(lossless):
    """Readers in threads (the runner streams a clip to several stages at once), each reading the
    clip in order from its own start, all get exactly their frames from one stage object."""
    path, truth = lossless
    stage, errors = VideoDecode(), []
    barrier = threading.Barrier(3)

    def read_in_order(first: int) -> None:
        barrier.wait()
        try:
            for _ in range(3):
                for start in range(first, 37, 4):
                    stop = min(start + 4, 37)
                    frames = stage.process(start, stop, {"video": path}, {}, None)["frames"]
                    np.testing.assert_array_equal(frames, truth[start:stop])
        except Exception as exc:  # noqa: BLE001 - reported by the main thread
            errors.append(exc)

    threads = [threading.Thread(target=read_in_order, args=(first,)) for first in (0, 1, 2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == []
    readers = list(stage._readers.values())
    assert len(readers) == 3  # one decoder per thread
    stage.close(None)
    assert stage._readers == {}
    for reader in readers:  # each decoder's file is closed: its container refuses to decode
        with pytest.raises(AssertionError, match="not open"):
            next(reader._container.demux())


def test_h264_writer_is_browser_friendly_close_and_bit_exact(tmp_path):
    truth = synthetic_frames(0, 20, width=63, height=47)  # odd sizes: padded to even
    paths = [tmp_path / f"{name}.mp4" for name in "abcd"]
    for path in paths:
        with VideoWriter(path, fps=25, width=63, height=47, codec="h264", crf=12) as writer:
            writer.write(truth[:7])
            writer.write(truth[7:])
    assert len({path.read_bytes() for path in paths}) == 1
    data = paths[0].read_bytes()
    assert data.index(b"moov") < data.index(b"mdat")  # +faststart: playable while downloading
    with av.open(str(paths[0])) as container:
        stream = container.streams.video[0]
        assert (stream.codec_context.name, stream.codec_context.pix_fmt) == ("h264", "yuv420p")
        assert stream.average_rate == Fraction(25)
    decoded = _decode_all(paths[0])
    assert decoded.shape == (20, 48, 64, 3)
    # 4:2:0 halves chroma resolution (the pattern's hue wraps are sharp): judge luma.
    assert _psnr(luma_opencv(decoded[:, :47, :63]), luma_opencv(truth)) > 38
    # The padding row/column repeat the last ones (not black).
    assert np.abs(decoded[:, 47].astype(int) - decoded[:, 46]).mean() < 4
    assert np.abs(decoded[:, :, 63].astype(int) - decoded[:, :, 62]).mean() < 4


def test_ffv1_writer_is_lossless_for_rgb_and_gray(tmp_path):
    truth = synthetic_frames(0, 5, width=33, height=21)
    with VideoWriter(tmp_path / "c.mkv", fps=10, width=33, height=21, codec="ffv1", crf=0) as writer:
        writer.write(truth)
    np.testing.assert_array_equal(_decode_all(tmp_path / "c.mkv"), truth)
    gray = truth[..., :1]
    with VideoWriter(tmp_path / "g.mkv", fps=10, width=33, height=21, codec="ffv1", crf=0) as writer:
        writer.write(gray)
    np.testing.assert_array_equal(_decode_all(tmp_path / "g.mkv"), np.repeat(gray, 3, axis=-1))


def test_writer_rejects_bad_frames_and_options(tmp_path):
    with pytest.raises(StageError, match="crf"):
        VideoWriter(tmp_path / "x.mp4", fps=25, width=8, height=8, crf=60)
    with pytest.raises(StageError, match="unknown codec"):
        VideoWriter(tmp_path / "x.mp4", fps=25, width=8, height=8, codec="vp9")
    with VideoWriter(tmp_path / "y.mp4", fps=25, width=8, height=8) as writer:
        with pytest.raises(StageError, match=r"expected frames \(B, 8, 8, 3 or 1\) uint8"):
            writer.write(np.zeros((1, 8, 8, 3), np.float32))


def test_write_video_stage_encodes_a_stream(tmp_path, lossless):
    path, truth = lossless
    ranges = chunk_ranges(37, 16)
    for s, e in ranges:
        np.save(tmp_path / f"{s}.npy", truth[s:e])
    stream = NpyStream(StreamInfo(37, 30000 / 1001, 64, 48), ranges, [tmp_path / f"{s}.npy" for s, _ in ranges])
    out = tmp_path / "files"
    done = []
    ctx = Context("cpu", files_dir=lambda port: out, progress=done.append)
    out.mkdir()
    defaults = {param.name: param.default for param in WriteVideo.params}
    WriteVideo().run({"frames": stream}, {**defaults, "codec": "ffv1", "filename": "clip"}, ctx)
    np.testing.assert_array_equal(_decode_all(out / "clip.mkv"), truth)
    assert sum(done) == 37


@pytest.mark.parametrize("name", ["../../x", "/abs", "a/b", ".", "..", "", ".hidden", "x" * 300])
def test_a_video_filename_that_is_not_a_plain_name_is_refused_at_load(name):
    """Refused when the pipeline is loaded (exit 2), one line of bounded length, before
    anything runs."""
    from runner.config import ConfigError, load_pipeline
    from runner.registry import Registry

    with pytest.raises(ConfigError) as info:
        load_pipeline(REPO / "pipeline.yaml", Registry.from_entry_points(), overrides=[f"video.filename={name}"])
    [issue] = info.value.issues
    assert str(issue).startswith("--set: video.filename: wrong value: expected filename matching ")
    assert len(str(issue)) < 300


def test_gray_matches_bt601_weights(lossless):
    _, truth = lossless
    stream = type("S", (), {"read": lambda self, s, e: truth[s:e]})()
    gray = ImageGray().process(3, 9, {"frames": stream}, {}, None)["frames"]
    expected = truth[3:9].astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    assert gray.shape == (6, 48, 64, 1) and gray.dtype == np.uint8
    assert np.abs(gray[..., 0] - expected).max() <= 1.0


def _zero_frame_clip(path: Path) -> None:
    container = av.open(str(path), "w")
    stream = container.add_stream("libx264", rate=25)
    stream.width, stream.height, stream.pix_fmt = 16, 16, "yuv420p"
    container.start_encoding()
    container.close()


def _bgr4_clip(path: Path) -> None:
    """A rawvideo NUT file in bgr4 (4-bit packed), a pixel format swscale cannot convert."""
    container = av.open(str(path), "w", format="nut")
    stream = container.add_stream("rawvideo", rate=25)
    stream.width, stream.height, stream.pix_fmt = 16, 16, "bgr4"
    frame = av.VideoFrame(16, 16, "bgr4")
    frame.pts = 0
    container.mux(stream.encode(frame))
    container.mux(stream.encode(None))
    container.close()


def _damaged(path: Path, tiny: Path, how: str) -> None:
    data = bytearray(tiny.read_bytes())
    if how == "truncated":
        data = data[: len(data) * 2 // 3]
    else:
        mid = len(data) // 2
        data[mid : mid + 3000] = np.random.default_rng(0).integers(0, 256, 3000, dtype=np.uint8).tobytes()
    path.write_bytes(bytes(data))


@pytest.mark.parametrize(
    "kind, words",
    [
        ("missing", "no such file"),
        ("text", "not a readable video"),
        ("empty", "contains no video frames"),
        ("truncated", "corrupt or truncated"),
        ("corrupt", "corrupt or truncated"),
        ("bgr4", "unsupported pixel format bgr4"),
    ],
)
def test_bad_input_is_one_line_stage_error_naming_the_file(tmp_path, kind, words):
    tiny = tmp_path / "tiny.mp4"
    write_clip(tiny, frames=24, width=64, height=48)
    path = tmp_path / f"bad-{kind.replace(' ', '-')}.mp4"
    if kind == "text":
        path.write_text("not a video\n" * 50)
    elif kind == "empty":
        _zero_frame_clip(path)
    elif kind in ("truncated", "corrupt"):
        _damaged(path, tiny, kind)
    elif kind == "bgr4":
        path = path.with_suffix(".nut")
        _bgr4_clip(path)
    stage = VideoDecode()
    with pytest.raises(StageError) as info:
        probe(path)
        # Damage the probe tolerates shows up while decoding.
        stage.process(0, probe(path).frames, {"video": path}, {}, None)
    message = str(info.value)
    assert str(path) in message and words in message and "\n" not in message


def _clip_with_timestamps(path: Path, pts_ms: list[int]) -> None:
    """An FFV1 MKV of gray frames shown at ``pts_ms`` (milliseconds)."""
    with av.open(str(path), "w") as container:
        stream = container.add_stream("ffv1", rate=25)
        stream.width, stream.height, stream.pix_fmt = 16, 16, "bgr0"
        stream.codec_context.time_base = Fraction(1, 1000)
        for i, pts in enumerate(pts_ms):
            frame = av.VideoFrame.from_ndarray(np.full((16, 16, 3), 10 * i, np.uint8), format="rgb24")
            frame.pts, frame.time_base = pts, Fraction(1, 1000)
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def test_variable_frame_rate_is_one_warning_line(tmp_path, caplog):
    constant, variable = tmp_path / "cfr.mkv", tmp_path / "vfr.mkv"
    _clip_with_timestamps(constant, [40 * i for i in range(8)])
    _clip_with_timestamps(variable, [0, 40, 80, 120, 300, 340, 380, 420])
    with caplog.at_level("WARNING"):
        assert probe(constant).frames == 8
        assert caplog.records == []
        assert probe(variable).frames == 8
    assert len(caplog.records) == 1
    assert str(variable) in caplog.text and "variable frame rate" in caplog.text and "constant" in caplog.text


def _with_display_rotation(path: Path, out: Path, a: int, b: int, c: int, d: int) -> Path:
    """A copy of an mp4 whose track header (``tkhd``) carries the rotation matrix
    ``[[a, b], [c, d]]`` (as a phone writes for a portrait clip: landscape pixels plus a
    display matrix)."""
    import struct

    data = bytearray(path.read_bytes())
    at = data.find(b"tkhd")
    version = data[at + 4]
    matrix = at + 8 + (20 if version == 0 else 32) + 16  # times, track id, duration; reserved, layer, ...
    assert struct.unpack(">9i", data[matrix : matrix + 36])[:5] == (65536, 0, 0, 0, 65536)  # identity before
    data[matrix : matrix + 36] = struct.pack(">9i", a << 16, b << 16, 0, c << 16, d << 16, 0, 0, 0, 1 << 30)
    out.write_bytes(bytes(data))
    return out


@pytest.mark.parametrize("matrix, turns", [((0, 1, -1, 0), -1), ((0, -1, 1, 0), 1), ((-1, 0, 0, -1), 2)])
def test_phone_display_rotation_is_applied(tmp_path, matrix, turns):
    """A display matrix in the track header (a phone's portrait clip) turns the decoded frames
    upright, as players show them; the stream's size is the upright one."""
    plain = write_clip(tmp_path / "plain.mp4", frames=5, width=64, height=48, crf=0)
    rotated = _with_display_rotation(plain, tmp_path / "rotated.mp4", *matrix)
    stage = VideoDecode()
    info = stage.stream_info({"video": rotated}, {})
    upright = np.rot90(_decode_all(plain), k=turns, axes=(1, 2))
    assert (info.height, info.width) == upright.shape[1:3]
    frames = VideoDecode().process(0, 5, {"video": rotated}, {}, None)["frames"]
    np.testing.assert_array_equal(frames, upright)


def _clip_with_audio(path: Path, *, frames: int, fps: int, audio_codec: str, sample_rate: int = 48000) -> np.ndarray:
    """An H.264 clip with a 440 Hz tone in ``audio_codec``; returns the tone's samples (mono)."""
    images = synthetic_frames(0, frames, width=64, height=48)
    tone = (0.3 * np.sin(2 * np.pi * 440 * np.arange(frames * sample_rate // fps) / sample_rate)).astype(np.float32)
    with av.open(str(path), "w") as container:
        video = container.add_stream("libx264", rate=fps)
        video.width, video.height, video.pix_fmt = 64, 48, "yuv420p"
        audio = container.add_stream(audio_codec, rate=sample_rate, layout="mono")
        for image in images:
            container.mux(video.encode(av.VideoFrame.from_ndarray(image, format="rgb24")))
        step = 1024
        for k in range(0, len(tone), step):
            block = tone[k : k + step]
            frame = av.AudioFrame.from_ndarray(block[None, :], format="fltp", layout="mono")
            frame.sample_rate, frame.pts = sample_rate, k
            container.mux(audio.encode(frame))
        container.mux(video.encode(None))
        container.mux(audio.encode(None))
    return images


def _audio_packets(path: Path) -> list[bytes]:
    with av.open(str(path)) as container:
        if not container.streams.audio:
            return []
        return [bytes(p) for p in container.demux(container.streams.audio[0]) if p.size]


def test_write_video_copies_the_clips_audio_unchanged(tmp_path):
    """The result plays with the performer's sound: the clip's AAC packets are copied as they are,
    the video is the frames written, and the audio lasts as long as the video."""
    clip = tmp_path / "talk.mp4"
    images = _clip_with_audio(clip, frames=25, fps=25, audio_codec="aac")
    for name, source in (("result.mp4", clip), ("silent.mp4", None)):
        with VideoWriter(tmp_path / name, fps=25, width=64, height=48, audio_from=source) as writer:
            writer.write(images)
    with av.open(str(tmp_path / "result.mp4")) as result:
        assert result.streams.audio[0].codec_context.name == "aac"
        audio_s = float(result.streams.audio[0].duration * result.streams.audio[0].time_base)
        assert abs(audio_s - 1.0) < 0.05
    assert _audio_packets(tmp_path / "result.mp4") == _audio_packets(clip)
    np.testing.assert_array_equal(_decode_all(tmp_path / "result.mp4"), _decode_all(tmp_path / "silent.mp4"))


def test_audio_an_mp4_cannot_hold_is_left_out_with_a_warning(tmp_path, caplog):
    clip = tmp_path / "talk.mkv"
    images = _clip_with_audio(clip, frames=10, fps=25, audio_codec="pcm_s16le")
    with VideoWriter(tmp_path / "result.mp4", fps=25, width=64, height=48, audio_from=clip) as writer:
        writer.write(images)
    assert _audio_packets(tmp_path / "result.mp4") == []
    assert any("pcm_s16le" in r.getMessage() and "not copied" in r.getMessage() for r in caplog.records)
    with VideoWriter(tmp_path / "result.mkv", fps=25, width=64, height=48, codec="ffv1", audio_from=clip) as writer:
        writer.write(images)
    assert _audio_packets(tmp_path / "result.mkv") == _audio_packets(clip)
