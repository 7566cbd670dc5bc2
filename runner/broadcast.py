"""Frames of one frame stage handed to every reader as they are computed, kept in memory only
until each reader has passed them (:class:`Broadcast`).

The cache stores no frames (docs/runner.md, "Scheduling"): a frame stage's chunk is computed
once, offered here, and taken by each stage reading it at the same time. A *reader* is a stage
name registered with :meth:`Broadcast.join` when it starts reading and removed with
:meth:`Broadcast.leave` when it stops; its *position* is the first chunk it may still ask for
(:meth:`Broadcast.advance`). A chunk is kept while a reader's position is at or before it, and
dropped once every reader has passed it. A chunk asked for after it was dropped (a reader that
joined late, reads out of order, or a later stage) is computed again by the caller.

Bounded memory: before a chunk is computed, :meth:`Broadcast.wait_room` waits while it lies
``keep`` or more chunks past the slowest reader's position. Each reader is *driven* by one
thread (the thread of the stage reading, which also computes the chunks of the stages it reads
through); a thread never waits for the readers it drives, so one thread that loads a stage's
bundles before reading its frames does not wait for itself (those chunks are then held until it
reads them). The slowest reader never waits (its chunk lies within ``keep`` of its own
position), so readers that keep reading always progress.

*Producer* threads compute the chunks in order while readers are registered
(:meth:`Broadcast.produce`, :meth:`Broadcast.room_to_produce`), so that readers only take what
they computed and no reader's own work (an encoder) holds up the chunks the others wait for. A
reader needing a chunk waits for it (:meth:`Broadcast.wait_turn`), and computes it itself only
when the producers cannot reach it: the readers holding them back are driven by the reader's
own thread (or it computes inside :func:`unbounded`), or no producer runs.
"""

from __future__ import annotations

import contextlib
import threading
from collections import Counter
from collections.abc import Callable, Iterator
from typing import Any

from runner.timing import waiting

_unbounded = threading.local()


@contextlib.contextmanager
def unbounded() -> Iterator[None]:
    """Chunks computed on this thread inside the block do not wait for room: for a reader that
    computes one chunk before it reads (those the others computed meanwhile are at most ``keep``)."""
    outer = getattr(_unbounded, "on", False)
    _unbounded.on = True
    try:
        yield
    finally:
        _unbounded.on = outer


class Broadcast:
    """The computed chunks of one stage's ``frames`` outputs, shared by its readers.

    Parameters
    ----------
    keep : how many chunks past the slowest reader's position may be computed before the
        computing thread waits (at least the chunks one read spans, plus one).
    """

    def __init__(self, *, keep: int):
        if keep < 1:
            raise ValueError(f"keep must be >= 1, got {keep}")
        self.keep = keep
        self._held: dict[int, dict[str, Any]] = {}  # chunk -> {port: frames (B, H, W, C)}
        self._position: dict[str, int] = {}  # reader -> first chunk it may still ask for
        self._joined: Counter[str] = Counter()  # reader -> how many times joined (several runs of it)
        self._drivers: dict[str, set[threading.Thread]] = {}  # reader -> the threads that read for it
        self._changed = threading.Condition()
        self._producers: list[threading.Thread] = []  # the threads computing the chunks in order

    def join(self, reader: str, driver: threading.Thread) -> None:
        """Register ``reader``, read by thread ``driver`` from the first chunk on."""
        with self._changed:
            self._joined[reader] += 1
            self._position.setdefault(reader, 0)
            self._drivers.setdefault(reader, set()).add(driver)

    def leave(self, reader: str, driver: threading.Thread) -> None:
        """Unregister ``reader`` as read by ``driver`` (it finished, or reads no more in order)."""
        with self._changed:
            if self._joined[reader] > 0:
                self._joined[reader] -= 1
                self._drivers[reader].discard(driver)
            if self._joined[reader] == 0:
                self._joined.pop(reader, None)
                self._drivers.pop(reader, None)
                self._position.pop(reader, None)
                self._drop()

    def advance(self, reader: str, chunk: int) -> None:
        """``reader`` will ask for no chunk before ``chunk`` any more (no effect for a stage
        that is not registered, or for a position it already passed)."""
        with self._changed:
            if reader in self._position and chunk > self._position[reader]:
                self._position[reader] = chunk
                self._drop()

    def wait_room(self, chunk: int) -> None:
        """Wait until ``chunk`` lies less than ``keep`` chunks past the position of every
        reader that the calling thread does not drive (at once inside :func:`unbounded`)."""
        me = threading.current_thread()
        with waiting(), self._changed:
            self._changed.wait_for(lambda: self._room(chunk, me))

    def _room(self, chunk: int, me: threading.Thread | None) -> bool:
        """Whether ``chunk`` lies less than ``keep`` chunks past the position of every reader
        that thread ``me`` does not drive (None: of every reader)."""
        if me is not None and getattr(_unbounded, "on", False):
            return True
        others = [p for reader, p in self._position.items() if me not in self._drivers.get(reader, ())]
        return not others or chunk < min(others) + self.keep

    def produce(self, producers: list[threading.Thread]) -> bool:
        """Make ``producers`` the threads computing the chunks in order, unless some already
        run (False: start nothing)."""
        with self._changed:
            if self._producers:
                return False
            self._producers = list(producers)
            return True

    def room_to_produce(self, chunk: int) -> bool:
        """The producer: wait until ``chunk`` lies less than ``keep`` chunks past every reader's
        position; False (stop producing) once no reader is registered or :meth:`stop` was called."""
        with self._changed:
            self._changed.wait_for(lambda: not self._producers or not self._position or self._room(chunk, None))
            return bool(self._producers) and bool(self._position)

    def stop(self) -> list[threading.Thread]:
        """No more producing; the producer threads (to join)."""
        with self._changed:
            producers, self._producers = self._producers, []
            self._changed.notify_all()
            return producers

    def wait_turn(self, chunk: int, resolved: Callable[[], bool]) -> None:
        """A reader needs ``chunk``: wait until it is ``resolved()`` or this thread has to compute
        it: it is a producer, none runs, or they cannot reach ``chunk`` (every registered
        reader counted) while the calling thread can (it drives the readers holding them back,
        or computes inside :func:`unbounded`)."""
        me = threading.current_thread()
        with waiting(), self._changed:
            self._changed.wait_for(
                lambda: (
                    resolved()
                    or not self._producers
                    or me in self._producers
                    or (not self._room(chunk, None) and self._room(chunk, me))
                )
            )

    def resolved(self) -> None:
        """A chunk was resolved: wake the readers waiting for their turn."""
        with self._changed:
            self._changed.notify_all()

    def offer(self, chunk: int, frames: dict[str, Any]) -> None:
        """Chunk ``chunk`` was computed: keep its frames (port -> array) while a reader's
        position is at or before it."""
        with self._changed:
            if any(position <= chunk for position in self._position.values()):
                self._held[chunk] = frames

    def take(self, chunk: int, port: str) -> Any | None:
        """Frames of ``port`` in ``chunk`` if they are kept, else None (compute them again)."""
        with self._changed:
            held = self._held.get(chunk)
            return None if held is None else held[port]

    def readers(self) -> list[str]:
        """The registered readers."""
        with self._changed:
            return list(self._position)

    def held(self) -> list[int]:
        """The chunks kept now, in order."""
        with self._changed:
            return sorted(self._held)

    def _drop(self) -> None:
        """Drop the chunks every reader passed, and wake computing threads waiting for room."""
        low = min(self._position.values(), default=None)
        for chunk in [c for c in self._held if low is None or c < low]:
            del self._held[chunk]
        self._changed.notify_all()
