"""Frame streams for calling stages directly (in memory, or chunks in ``.npy`` files) and a stage context."""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from runner.lifecycle import opened
from runner.stage import Context, FrameStage, StreamInfo
from runner.streams import ChunkedStream


class MemoryStream:
    """Frames ``(T, H, W, C)`` held in memory, read with edge replication like the runner's streams;
    ``reads`` counts the chunks handed out."""

    def __init__(self, frames: np.ndarray, *, fps: float = 25.0, chunk: int = 4) -> None:
        self.frames = frames
        self.chunk = chunk
        self.info = StreamInfo(frames=len(frames), fps=fps, width=frames.shape[2], height=frames.shape[1])
        self.reads = 0

    def read(self, start: int, stop: int) -> np.ndarray:
        return self.frames[np.clip(np.arange(start, stop), 0, len(self.frames) - 1)]

    def chunks(self) -> Iterator[tuple[int, np.ndarray]]:
        for start in range(0, len(self.frames), self.chunk):
            self.reads += 1
            yield start, self.read(start, min(start + self.chunk, len(self.frames)))


class NpyStream(ChunkedStream):
    """Chunks stored as ``.npy`` files, one per chunk, read when touched (``files[i]`` holds the
    frames ``ranges[i]``, ``(stop - start, H, W, C)``)."""

    def __init__(self, info: StreamInfo, ranges: list[tuple[int, int]], files: list[Path]) -> None:
        super().__init__(info, ranges)
        self._files = files

    def chunk(self, index: int, *, mmap: bool = False) -> np.ndarray:
        return np.load(self._files[index], mmap_mode="r" if mmap else None, allow_pickle=False)


def files_context(root: Path) -> Context:
    """A CPU context whose ``files`` ports are folders ``root/<port>``."""
    return Context(device="cpu", files_dir=lambda port: root / port)


def process_once(stage: FrameStage, start: int, stop: int, inputs: dict, params: dict, ctx: Context) -> dict:
    """``stage.process`` of frames ``[start, stop)`` outside a run: the stage opened on
    ``ctx.device`` first and closed after (:func:`runner.lifecycle.opened`)."""
    with opened(stage, inputs, params, device=ctx.device):
        return stage.process(start, stop, inputs, params, ctx)
