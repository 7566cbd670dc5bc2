"""Byte-deterministic writers: npz without timestamps, PNG, points CSV, H.264 mp4 (PyAV, one thread)."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import av
import cv2
import numpy as np

FIXED_DATE = (1980, 1, 1, 0, 0, 0)


def save_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write ``arrays`` as an uncompressed-member, deflated ``.npz`` with fixed zip timestamps,
    sorted keys and no pickled objects (``np.load(path, allow_pickle=False)`` reads it)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for key in sorted(arrays):
            arr = np.asarray(arrays[key])
            if arr.dtype == object:
                raise TypeError(f"{key}: object arrays are not allowed")
            buf = io.BytesIO()
            np.lib.format.write_array(buf, arr if arr.flags.c_contiguous else arr.copy(order="C"), allow_pickle=False)
            info = zipfile.ZipInfo(f"{key}.npy", date_time=FIXED_DATE)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, buf.getvalue())


def write_png(path: Path, image: np.ndarray) -> None:
    """Write an RGB ``(H, W, 3) uint8`` image as PNG."""
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, data = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        raise OSError(f"cannot encode {path}")
    path.write_bytes(data.tobytes())


def write_points_csv(
    path: Path, names: tuple[str, ...] | list[str], points: np.ndarray, *, frame_size: tuple[int, int] | None = None
) -> None:
    """Write ``name,x,y`` rows (px, 6 decimals) for ``points`` ``(N, 2)``; with ``frame_size``
    ``(W, H)``, first a comment line ``# frame_size: W H`` (the frame the points belong to)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    header = [f"# frame_size: {frame_size[0]} {frame_size[1]}"] if frame_size is not None else []
    lines = header + ["name,x,y"] + [f"{n},{x:.6f},{y:.6f}" for n, (x, y) in zip(names, np.asarray(points, dtype=np.float64))]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def write_named_rows(path: Path, names: tuple[str, ...], rows: np.ndarray, columns: tuple[str, ...]) -> None:
    """Write ``name,<columns>`` CSV rows with 6 decimals."""
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = [",".join(("name", *columns))]
    lines += [",".join([n] + [f"{v:.6f}" for v in row]) for n, row in zip(names, np.asarray(rows, dtype=np.float64))]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


class Mp4Writer:
    """H.264 (libx264, yuv420p) mp4 writer whose bytes are repeatable (one thread, no mb-tree)."""

    def __init__(self, path: Path, size: tuple[int, int], fps: int, *, crf: int = 18) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self.container = av.open(str(path), mode="w", format="mp4")
        self.stream = self.container.add_stream("libx264", rate=fps)
        self.stream.width, self.stream.height = size
        self.stream.pix_fmt = "yuv420p"
        self.stream.codec_context.thread_count = 1
        # mb-tree and the lookahead use floating point whose results change with the FPU state
        # other libraries (BLAS) leave behind; without them the output bytes are repeatable.
        self.stream.codec_context.options = {
            "crf": str(crf),
            "preset": "medium",
            "threads": "1",
            "x264-params": "mbtree=0:rc-lookahead=0:sync-lookahead=0",
        }

    def write(self, image: np.ndarray) -> None:
        """Encode one RGB ``(H, W, 3) uint8`` frame. The RGB -> YUV 4:2:0 conversion (BT.601,
        limited range) is OpenCV's: swscale's result depends on buffer alignment, so bytes vary."""
        yuv = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2YUV_I420)
        frame = av.VideoFrame.from_ndarray(yuv, format="yuv420p")
        for packet in self.stream.encode(frame):
            self.container.mux(packet)

    def close(self) -> None:
        for packet in self.stream.encode():
            self.container.mux(packet)
        self.container.close()
