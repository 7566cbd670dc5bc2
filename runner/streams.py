"""Frame streams handed to stages: chunks shared as they are computed, or computed on demand.

Both implement :class:`runner.stage.FrameStream`: ``read(start, stop)`` with indices clamped to
the clip by edge replication, and ``chunks()`` over the whole clip in order. Only the chunks a
read touches are loaded, so no stage holds a whole clip of images in memory.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Iterator

import numpy as np

from runner.stage import StreamInfo
from runner.timing import waiting


def chunk_ranges(frames: int, chunk_frames: int) -> list[tuple[int, int]]:
    """``[(start, stop), ...]`` covering ``[0, frames)`` in chunks of ``chunk_frames``."""
    return [(s, min(s + chunk_frames, frames)) for s in range(0, frames, chunk_frames)]


class ChunkedStream:
    """A frame stream made of consecutive chunks; subclasses say how a chunk is obtained."""

    def __init__(self, info: StreamInfo, ranges: list[tuple[int, int]]):
        self.info = info
        self.ranges = ranges
        self._starts = np.array([s for s, _ in ranges], dtype=np.int64)

    def chunk(self, index: int, *, mmap: bool = False) -> np.ndarray:
        raise NotImplementedError

    def rows(self, index: int, lo: int, hi: int) -> np.ndarray:
        """Frames ``[lo, hi)`` of chunk ``index`` (counted from the chunk's first frame)."""
        return self.chunk(index, mmap=True)[lo:hi]

    def asked(self, index: int) -> None:
        """Called before a read whose first chunk is ``index``: the reader will ask for no
        earlier chunk (unless it reads out of order)."""

    def read(self, start: int, stop: int) -> np.ndarray:
        """Frames ``[start, stop)`` as ``(stop - start, H, W, C)``; indices outside the clip
        repeat the first or last frame."""
        wanted = np.clip(np.arange(start, stop), 0, self.info.frames - 1)
        if wanted.size == 0:
            raise ValueError(f"empty frame range [{start}, {stop})")
        which = np.searchsorted(self._starts, wanted, side="right") - 1
        self.asked(int(which.min()))
        parts = []
        for index in np.unique(which):
            rows = wanted[which == index] - self.ranges[index][0]
            frames = self.rows(int(index), int(rows.min()), int(rows.max()) + 1)
            rows = rows - rows.min()
            # A slice (a view) where no frame repeats, so that the result is copied only once.
            parts.append(frames[rows[0] : rows[-1] + 1] if rows[-1] - rows[0] + 1 == rows.size else frames[rows])
        return np.concatenate(parts) if len(parts) > 1 else np.array(parts[0])

    def chunks(self) -> Iterator[tuple[int, np.ndarray]]:
        for index, (start, _) in enumerate(self.ranges):
            self.asked(index)
            yield start, self.chunk(index)


class SharedStream(ChunkedStream):
    """One reader's view of a frame stage's chunks shared as they are computed
    (:class:`runner.broadcast.Broadcast`): ``fetch(index, lo, hi)`` gives frames ``[lo, hi)`` of
    a chunk (kept, or computed), ``asked(index)`` tells the producer where this reader is."""

    def __init__(
        self,
        info: StreamInfo,
        ranges: list[tuple[int, int]],
        fetch: Callable[[int, int, int], np.ndarray],
        asked: Callable[[int], None],
    ):
        super().__init__(info, ranges)
        self._fetch, self._asked = fetch, asked

    def chunk(self, index: int, *, mmap: bool = False) -> np.ndarray:
        start, stop = self.ranges[index]
        return self._fetch(index, 0, stop - start)

    def rows(self, index: int, lo: int, hi: int) -> np.ndarray:
        return self._fetch(index, lo, hi)

    def asked(self, index: int) -> None:
        self._asked(index)


class ComputedStream(ChunkedStream):
    """Chunks computed when first read by ``compute(index)``, strictly in order where possible
    (a decoder then never seeks back), keeping the last few in memory for temporal windows and
    parallel readers. A chunk before the in-order position that is no longer kept (a reader
    behind the others, or picking frames here and there) is computed on the caller's thread
    outside the stream's locks and not kept: it neither moves the position back nor holds up the
    readers in order while it is computed. A chunk past the position starts the order there.
    Thread-safe.

    With ``read_ahead``, once a reader has a chunk in order, the next one is computed on a
    thread of the stream's own while the reader works on this one (a decoder's frames are ready
    when the tracker asks for them): one thread for the stream's life, so that a stage keeping
    per-thread state (``video.decode``'s decoder) goes on decoding where it stopped; at most one
    chunk ahead of the furthest in-order read, so at most one more chunk is held. A reader asking
    for that chunk waits for it; a failure computing it is raised to that reader. Only for a
    stage that reads no frames: its chunks depend on nothing another thread must drive.
    """

    def __init__(
        self,
        info: StreamInfo,
        ranges: list[tuple[int, int]],
        compute: Callable[[int], np.ndarray],
        *,
        keep: int = 3,
        read_ahead: bool = False,
    ):
        super().__init__(info, ranges)
        self._compute = compute
        self._keep = keep
        self._recent: OrderedDict[int, np.ndarray] = OrderedDict()
        self._next = 0
        self._state = threading.Lock()  # guards _recent, _next and the read-ahead's fields, never held while computing
        self._order = threading.Lock()  # held while computing in order
        self._read_ahead = read_ahead
        self._ahead_ready = threading.Condition(self._state)  # the read-ahead's chunk is done (or failed)
        self._queued: int | None = None  # the chunk the read-ahead thread computes next
        self._failed: dict[int, BaseException] = {}  # read-ahead failures, raised to the chunk's reader
        self._ahead: threading.Thread | None = None
        self._stopped = False  # no more read-ahead (:meth:`stop`)

    def chunk(self, index: int, *, mmap: bool = False) -> np.ndarray:
        with waiting(), self._ahead_ready:  # the read-ahead thread's chunk
            while self._queued == index:
                self._ahead_ready.wait()
            if index in self._failed:
                raise self._failed.pop(index)
        frames = self._kept(index)
        if frames is None:
            with self._order:
                frames = self._kept(index)
                if frames is None:
                    for i in range(self._next if index < self._next + self._keep else index, index + 1):
                        frames = self._compute(i)
                        self._keep_chunk(i, frames)
        if self._read_ahead:
            self._queue(index + 1)
        return frames  # type: ignore[return-value]  # computed above when not kept (the range ends at index)

    def _keep_chunk(self, index: int, frames: np.ndarray) -> None:
        """Keep chunk ``index`` (computed in order) and move the in-order position past it."""
        with self._state:
            self._recent[index] = frames
            while len(self._recent) > self._keep:
                self._recent.popitem(last=False)
            self._next = index + 1

    def _queue(self, index: int) -> None:
        """Have the read-ahead thread compute chunk ``index`` if it is the next in order."""
        with self._ahead_ready:
            if self._stopped or index >= len(self.ranges) or index != self._next or self._queued is not None:
                return
            self._queued = index
            if self._ahead is None:
                self._ahead = threading.Thread(target=self._compute_ahead, name="read-ahead", daemon=True)
                self._ahead.start()
            self._ahead_ready.notify_all()

    def _compute_ahead(self) -> None:
        """The read-ahead thread: compute each queued chunk in order; end after the last chunk."""
        last = False
        while not last:
            with self._ahead_ready:
                while self._queued is None and not self._stopped:
                    self._ahead_ready.wait()
                if self._queued is None:  # stopped
                    self._ahead = None
                    return
                index = self._queued
            last = index == len(self.ranges) - 1
            try:
                with self._order:
                    if index == self._next:  # else a reader computed it meanwhile
                        self._keep_chunk(index, self._compute(index))
            except BaseException as exc:  # noqa: BLE001 - raised to the reader of this chunk
                with self._state:
                    self._failed[index] = exc
            finally:
                with self._ahead_ready:
                    self._queued = None
                    if last:
                        self._ahead = None
                    self._ahead_ready.notify_all()

    def stop(self) -> None:
        """End the read-ahead: wait for the chunk it computes, if any, and queue no more (the
        stage is about to be closed, with the decoder that thread uses)."""
        with self._ahead_ready:
            self._stopped = True
            self._ahead_ready.notify_all()
            while self._queued is not None:
                self._ahead_ready.wait()

    def _kept(self, index: int) -> np.ndarray | None:
        """Chunk ``index`` if it is kept, else None; computes it at once, outside the locks and
        without keeping it, if it lies before the in-order position."""
        with self._state:
            if index in self._recent:
                self._recent.move_to_end(index)
                return self._recent[index]
            behind = index < self._next
        return self._compute(index) if behind else None
