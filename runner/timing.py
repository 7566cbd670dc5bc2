"""Each stage's own time: what its summary line and ``--log-json``'s ``stage`` event report.

A stage's seconds count its own computing: not the chunks of an upstream stage computed on its
thread while it reads them (those are the upstream's), and not the time its thread waits for
another thread's work (a chunk a producer thread computes, room in a broadcast: :func:`waiting`).
So a stage reading a stream while it is computed reports its own work, not the whole stream's
span, and no stage's seconds exceed the run's wall time.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterator

_clock = threading.local()


@contextlib.contextmanager
def own_time(add: Callable[[float, float], None]) -> Iterator[None]:
    """Time the block and pass ``add`` its wall seconds and this thread's CPU seconds, each
    minus those of timed blocks nested in it on this thread (chunks of an upstream stage
    computed while this one reads them), so that each stage's summary counts its own time only.
    The CPU seconds are of the Python thread: threads a library starts (x264's, OpenMP's) are
    not counted."""
    outer = getattr(_clock, "nested", (0.0, 0.0))
    _clock.nested = (0.0, 0.0)
    started, cpu = time.perf_counter(), time.thread_time()
    try:
        yield
    finally:
        elapsed, used = time.perf_counter() - started, time.thread_time() - cpu
        add(elapsed - _clock.nested[0], used - _clock.nested[1])
        _clock.nested = (outer[0] + elapsed, outer[1] + used)


@contextlib.contextmanager
def waiting() -> Iterator[None]:
    """A block in which this thread waits for another thread's work: its wall time is left out
    of the enclosing :func:`own_time` block's, as a nested block's is (its CPU is not counted
    either way: a waiting thread uses none)."""
    started = time.perf_counter()
    try:
        yield
    finally:
        nested = getattr(_clock, "nested", (0.0, 0.0))
        _clock.nested = (nested[0] + time.perf_counter() - started, nested[1])
