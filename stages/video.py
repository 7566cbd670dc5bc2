"""Video in and out (PyAV): the ``video.decode`` frame stage, a reusable :class:`VideoWriter`,
the ``write.video`` stage, and ``image.gray``, a trivial frame stage that exercises the runner.

Frames in memory are RGB ``uint8`` arrays ``(B, H, W, 3)`` (or ``(B, H, W, 1)`` grayscale).
Bad input (missing file, not a video, no frames, truncated or corrupt stream, a pixel format
that cannot be converted to RGB) raises :class:`runner.stage.StageError` naming the file.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator, Mapping
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from runner.stage import FILE_NAME, Context, FrameStage, Param, SequenceStage, StageError, StreamInfo
from stages.color import luma_opencv, rgb_to_ycbcr420, to_uint8

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only; imported where used, so that importing this module stays light
    import av

CODECS = {"h264": ("libx264", "yuv420p", ".mp4"), "ffv1": ("ffv1", "bgr0", ".mkv")}
# x264's presets, fastest first (docs/writers.md, "Encoder settings", measures them).
X264_PRESETS = ("ultrafast", "superfast", "veryfast", "faster", "fast", "medium", "slow", "slower", "veryslow")
# Audio codecs copied as they are into the MP4 (an MKV takes any): what browsers play from MP4.
MP4_AUDIO = frozenset({"aac", "mp3", "alac", "opus", "flac", "ac3"})
# H.264 colour tags (ISO/IEC 23091-2 code points): limited range, BT.709 primaries, sRGB curve.
_TV_RANGE, _BT709_PRIMARIES, _SRGB_TRC = 1, 1, 13


def _open(path: Path) -> tuple[av.container.InputContainer, av.video.stream.VideoStream]:
    """Open ``path`` and its first video stream, or raise a one-line :class:`StageError`."""
    import av

    if not path.is_file():
        raise StageError(f"{path}: no such file")
    try:
        container = av.open(str(path))
    except (av.FFmpegError, OSError) as exc:
        raise StageError(f"{path}: not a readable video ({_reason(exc)})") from None
    if not container.streams.video:
        container.close()
        raise StageError(f"{path}: contains no video frames (no video stream)")
    return container, container.streams.video[0]


def _reason(exc: BaseException) -> str:
    return getattr(exc, "strerror", None) or str(exc) or type(exc).__name__


def _to_rgb(frame: av.VideoFrame, path: Path) -> np.ndarray:
    """The frame as RGB ``(H, W, 3)`` uint8, upright: a display matrix (a phone's portrait clip
    stores landscape pixels and a rotation) is applied as FFmpeg's players do, by quarter turns
    (``frame.rotation`` is counterclockwise in degrees)."""
    import av

    try:
        rgb = frame.to_ndarray(format="rgb24")
    except (av.FFmpegError, OSError, ValueError) as exc:
        raise StageError(f"{path}: unsupported pixel format {frame.format.name} ({_reason(exc)})") from None
    turns = round((frame.rotation or 0) / 90) % 4
    return np.ascontiguousarray(np.rot90(rgb, k=turns)) if turns else rgb


def probe(path: Path) -> StreamInfo:
    """Frame count (counted by demuxing, not from header metadata), rate and size of the first
    video stream of ``path`` (upright, after its display rotation); decodes the first frame to
    check the pixel format converts.

    The pipeline's time fields are ``frame / fps`` (a constant rate). A clip whose frame
    durations differ by more than a tenth of the mean one (variable frame rate) is still
    processed, with one warning line saying that its timestamps are replaced by that
    constant rate.
    """
    import av

    container, stream = _open(path)
    with container:
        rate = stream.average_rate or stream.guessed_rate
        try:
            stamps = [packet.pts for packet in container.demux(stream) if packet.size]
            count = len(stamps)
            container.seek(0)
            first = next(container.decode(stream), None)
        except av.FFmpegError as exc:
            raise StageError(f"{path}: corrupt or truncated stream ({_reason(exc)})") from None
        if count == 0 or first is None:
            raise StageError(f"{path}: contains no video frames")
        if not rate:
            raise StageError(f"{path}: the video stream has no frame rate")
        height, width = _to_rgb(first, path).shape[:2]  # upright: a display rotation swaps them
        _warn_if_variable_rate(path, stamps, stream.time_base, float(rate))
        return StreamInfo(frames=count, fps=float(rate), width=width, height=height)


def _warn_if_variable_rate(path: Path, pts: list[int | None], time_base: Fraction | None, fps: float) -> None:
    """Log one warning if the frame durations (from the packets' presentation times ``pts``, in
    ``time_base`` s) vary by more than a tenth of a frame period at ``fps``."""
    if time_base is None or len(pts) < 3 or None in pts:
        return
    durations = np.diff(np.sort(np.asarray(pts, dtype=np.float64))) * float(time_base)
    if durations.max() - durations.min() > 0.1 / fps:
        logging.getLogger("stages.video").warning(
            "warning: %s: variable frame rate (frame durations %.4f..%.4f s); the outputs' time fields "
            "assume a constant %.3f fps (time_s = frame / fps)",
            path,
            durations.min(),
            durations.max(),
            fps,
        )


class _Reader:
    """Sequential decoder of one file: :meth:`read` returns the next frames; a read that does not
    continue where the last one stopped reopens the file and decodes up to its start."""

    def __init__(self, path: Path):
        self.path = path
        self.position = 0
        self._container, stream = _open(path)
        self._frames: Iterator[av.VideoFrame] = self._container.decode(stream)

    def read(self, start: int, stop: int) -> np.ndarray:
        import av

        if start < self.position:
            self.close()
            self.__init__(self.path)
        out = []
        try:
            while self.position < stop:
                frame = next(self._frames, None)
                if frame is None:
                    raise StageError(
                        f"{self.path}: truncated stream: frame {self.position} missing (expected at least {stop} frames)"
                    )
                if self.position >= start:
                    out.append(_to_rgb(frame, self.path))
                self.position += 1
        except av.FFmpegError as exc:
            raise StageError(f"{self.path}: corrupt or truncated stream at frame {self.position} ({_reason(exc)})") from None
        return np.stack(out)

    def close(self) -> None:
        self._container.close()


class VideoDecode(FrameStage):
    """Decode a clip to RGB frames, chunk by chunk (not cached: decoding is cheaper than
    reading raw frames back).

    Reentrant: each thread that calls :meth:`process` has its own decoder, so stages that
    read the clip concurrently (each in order) each decode sequentially instead of sharing one
    position; :meth:`close` closes them all.
    """

    name = "video.decode"
    version = "1"
    doc = "Decode the first video stream of a file into RGB uint8 frames (PyAV)."
    inputs = {"video": "video"}
    outputs = {"frames": "frames"}
    cached = False
    threading = "reentrant"

    def __init__(self) -> None:
        self._readers: dict[int, _Reader] = {}  # per thread (threading.get_ident()): its decoder

    def stream_info(self, inputs: Mapping[str, Any], params: Mapping[str, Any]) -> StreamInfo:
        return probe(Path(inputs["video"]))

    def process(
        self, start: int, stop: int, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context
    ) -> dict[str, Any]:
        """Frames ``[start, stop)`` as ``(stop - start, H, W, 3)`` uint8 RGB."""
        path = Path(inputs["video"])
        thread = threading.get_ident()
        reader = self._readers.get(thread)
        if reader is None or reader.path != path:
            if reader is not None:
                reader.close()
            reader = self._readers[thread] = _Reader(path)
        return {"frames": reader.read(start, stop)}

    def close(self, ctx: Context) -> None:
        """Close every thread's decoder."""
        while self._readers:
            self._readers.popitem()[1].close()


class ImageGray(FrameStage):
    """Luma of RGB frames (ITU-R BT.601 weights, OpenCV's ``COLOR_RGB2GRAY``)."""

    name = "image.gray"
    version = "1"
    doc = "Convert RGB frames to one-channel grayscale (BT.601 luma)."
    inputs = {"frames": "frames"}
    outputs = {"frames": "frames"}

    def process(
        self, start: int, stop: int, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context
    ) -> dict[str, Any]:
        """``(B, H, W, 3)`` uint8 RGB -> ``(B, H, W, 1)`` uint8, Y = 0.299 R + 0.587 G + 0.114 B."""
        return {"frames": luma_opencv(inputs["frames"].read(start, stop))[..., None]}


class VideoWriter:
    """Encode RGB (or grayscale) frames to a video file.

    Parameters
    ----------
    path
        Output file; ``.mp4`` for ``h264``, ``.mkv`` for ``ffv1`` is conventional.
    fps
        Frame rate (frames per second); stored as the nearest fraction with a denominator up to 1001 (an NTSC rate 30000/1001 from a decoded clip stays exact).
    width, height
        Frame size in px. H.264 4:2:0 needs even sizes: odd ones are padded by one row/column
        repeating the last, so the decoded video is ``(height + height % 2, width + width % 2)``.
    codec
        ``"h264"``: libx264, yuv420p, ``+faststart`` MP4 (plays in browsers).
        ``"ffv1"``: FFV1 lossless 8-bit RGB (decodes to exactly the frames written).
    crf
        x264 constant rate factor, 0 (lossless luma) .. 51; ignored by FFV1.
    preset
        x264 preset (``X264_PRESETS``): encoder CPU time against file size at the same ``crf``
        (the picture quality depends on ``crf``; docs/writers.md measures both). The class keeps
        x264's own default (``medium``) for source clips; ``write.video`` defaults to ``superfast``
        for its review copies. Ignored by FFV1.
    threads
        x264 threads, >= 1. They are slice threads (each frame is cut into ``threads`` slices
        encoded in parallel), so the bytes depend on the count: it is a fixed number, not "one
        per core". Ignored by FFV1.
    audio_from
        A clip whose first audio stream is copied into the file as it is (no re-encoding), its
        timestamps shifted so that the clip's first video frame is at time 0; None, a clip without
        audio, or (MP4) a codec outside ``MP4_AUDIO``: no audio (the last with a warning).

    H.264 colour: RGB is converted to Y'CbCr 4:2:0 with the BT.601 matrix, limited range
    (:func:`stages.color.rgb_to_ycbcr420`), and the stream says so, with the sRGB primaries
    (BT.709) and transfer curve
    (IEC 61966-2-1), so that players do not guess (many take untagged video of 720 lines or more
    as BT.709 and shift its colours).

    Output is bit-exact across runs (``+bitexact`` muxing, frame i at pts i).
    """

    def __init__(
        self,
        path: Path,
        *,
        fps: float,
        width: int,
        height: int,
        codec: str = "h264",
        crf: int = 18,
        preset: str = "medium",
        threads: int = 2,
        audio_from: Path | None = None,
    ):
        import av

        if codec not in CODECS:
            raise StageError(f"{path}: unknown codec {codec!r} (expected one of {', '.join(CODECS)})")
        if not 0 <= crf <= 51:
            raise StageError(f"{path}: crf must be within 0..51, got {crf}")
        if preset not in X264_PRESETS:
            raise StageError(f"{path}: unknown x264 preset {preset!r} (expected one of {', '.join(X264_PRESETS)})")
        if threads < 1:
            raise StageError(f"{path}: x264 threads must be >= 1, got {threads}")
        encoder, pix_fmt, _ = CODECS[codec]
        self.path, self.width, self.height = Path(path), width, height
        self._pad = (height % 2, width % 2) if codec == "h264" else (0, 0)
        options = {"fflags": "+bitexact"}
        if codec == "h264":
            options["movflags"] = "+faststart"
        self._container = av.open(str(path), "w", options=options)
        rate = Fraction(fps).limit_denominator(1001)
        self._time_base = 1 / rate
        self._stream = self._container.add_stream(encoder, rate=rate)
        self._stream.codec_context.time_base = self._time_base
        self._stream.width = width + self._pad[1]
        self._stream.height = height + self._pad[0]
        self._stream.pix_fmt = pix_fmt
        if codec == "h264":
            # MB-tree rate control is not bit-exact from run to run on small frames; without it
            # the encoder output is a function of the frames alone.
            self._stream.options = {"crf": str(crf), "preset": preset, "x264-params": "mbtree=0"}
            context = self._stream.codec_context
            context.thread_count = threads  # PyAV's thread type is SLICE: x264 sliced threads
            context.colorspace, context.color_range = av.video.reformatter.Colorspace.ITU601, _TV_RANGE
            context.color_primaries, context.color_trc = _BT709_PRIMARIES, _SRGB_TRC
        self._count = 0
        self._audio_in, self._audio_out = self._audio_source(audio_from, codec) if audio_from else (None, None)

    def _audio_source(self, clip: Path, codec: str) -> tuple[Any, Any]:
        """The clip's first audio stream and its copy in the output, or (None, None)."""
        source, _ = _open(clip)
        if not source.streams.audio:
            source.close()
            return None, None
        audio = source.streams.audio[0]
        if codec == "h264" and audio.codec_context.name not in MP4_AUDIO:
            logging.getLogger("runner.stage").warning(
                "%s: audio codec %s is not copied into the MP4 (copied: %s)",
                clip,
                audio.codec_context.name,
                ", ".join(sorted(MP4_AUDIO)),
            )
            source.close()
            return None, None
        return audio, self._container.add_stream_from_template(audio)

    def write(self, frames: np.ndarray) -> None:
        """Append frames ``(B, H, W, 3)`` uint8 RGB or ``(B, H, W, 1)`` uint8 gray."""
        if (
            frames.dtype != np.uint8
            or frames.ndim != 4
            or frames.shape[1:3] != (self.height, self.width)
            or frames.shape[3] not in (1, 3)
        ):
            raise StageError(
                f"{self.path}: expected frames (B, {self.height}, {self.width}, 3 or 1) uint8, got {frames.shape} {frames.dtype}"
            )
        if any(self._pad):
            frames = np.pad(frames, ((0, 0), (0, self._pad[0]), (0, self._pad[1]), (0, 0)), mode="edge")
        for image in frames:
            frame = self._frame(image)
            frame.pts = self._count
            frame.time_base = self._time_base
            self._count += 1
            self._container.mux(self._stream.encode(frame))

    def _frame(self, image: np.ndarray) -> av.VideoFrame:
        """One ``(H, W, 3|1)`` uint8 image as a frame of the stream's pixel format.

        H.264: converted by :func:`stages.color.rgb_to_ycbcr420` (OpenCV, outside the GIL)
        straight into a new frame's planes (no copy); the encoder then converts nothing.
        (``VideoFrame.from_numpy_buffer`` of an I420 array would save nothing and takes the
        height of a frame whose height is not a multiple of 4 wrongly, PyAV 18.) FFV1:
        swscale's RGB -> BGR0, exact, on one thread (the same rows every time; PyAV's implicit
        conversion inside ``encode()`` is not bit-exact from one run to the next).
        """
        import av

        if self._stream.pix_fmt == "yuv420p":
            frame = av.VideoFrame(image.shape[1], image.shape[0], "yuv420p")
            planes = (
                np.frombuffer(plane, np.uint8).reshape(plane.height, plane.line_size)[:, : plane.width] for plane in frame.planes
            )  # views of the frame's padded lines
            rgb_to_ycbcr420(image, out=tuple(planes))
            return frame
        if image.shape[2] == 1:
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image[:, :, 0]), format="gray")
        else:
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
        return frame.reformat(format=self._stream.pix_fmt, threads=1)

    def close(self) -> None:
        """Flush the encoder, copy the audio (if any) and finish the file."""
        if self._container is not None:
            self._container.mux(self._stream.encode(None))
            if self._audio_in is not None:
                self._copy_audio()
            self._container.close()
            self._container = None

    def _copy_audio(self) -> None:
        """Remux the source's audio packets, shifted so the source's first video frame is at 0
        and cut at the end of the video written."""
        source, audio = self._audio_in.container, self._audio_in
        video = source.streams.video[0]  # _open checked there is one
        start_s = float(video.start_time * video.time_base) if video.start_time is not None else 0.0
        end_s = self._count * float(self._time_base)
        shift = round(start_s / audio.time_base)
        for packet in source.demux(audio):
            if packet.dts is None or packet.pts is None:
                continue
            if float((packet.pts - shift) * audio.time_base) >= end_s:
                break
            packet.pts -= shift
            packet.dts -= shift
            packet.stream = self._audio_out
            self._container.mux(packet)
        source.close()
        self._audio_in = None

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class WriteVideo(SequenceStage):
    """Encode a frame stream to one video file (H.264 MP4 or FFV1 MKV)."""

    name = "write.video"
    version = "5"
    doc = "Encode frames (uint8, or float sRGB in [0, 1]) to a video file: H.264 MP4 or FFV1 MKV; audio copied from 'audio'."
    inputs = {"frames": "frames", "audio": "video"}
    optional_inputs = frozenset({"audio"})
    outputs = {"video": "files"}
    params = (
        Param("codec", str, "h264", "h264 (yuv420p MP4, plays in browsers) or ffv1 (lossless RGB MKV)", choices=tuple(CODECS)),
        Param("crf", int, 18, "x264 constant rate factor 0..51 (lower = better); ignored by ffv1", min=0, max=51),
        Param(
            "preset",
            str,
            "superfast",
            "x264 preset: encoder time against file size at the same crf (docs/writers.md); ignored by ffv1",
            choices=X264_PRESETS,
        ),
        Param("threads", int, 2, "x264 slice threads (the bytes depend on the count); ignored by ffv1", min=1, max=16),
        Param("filename", str, "video", "file name without extension", pattern=FILE_NAME),
    )

    def run(self, inputs: Mapping[str, Any], params: Mapping[str, Any], ctx: Context) -> dict[str, Any]:
        stream = inputs["frames"]
        info = stream.info
        path = ctx.files_dir("video") / f"{params['filename']}{CODECS[params['codec']][2]}"
        with VideoWriter(
            path,
            fps=info.fps,
            width=info.width,
            height=info.height,
            codec=params["codec"],
            crf=params["crf"],
            preset=params["preset"],
            threads=params["threads"],
            audio_from=inputs.get("audio"),
        ) as writer:
            for _, frames in stream.chunks():
                writer.write(to_uint8(frames))  # half floats: one SIMD pass (stages.color)
                ctx.progress(len(frames))
        return {"video": None}
