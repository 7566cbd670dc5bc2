"""A stage instance's lifecycle in one run: opened once before its first call, its calls
serialized if it declares ``threading = "single"``, closed once (docs/runner.md, "Stage
lifecycle and threads"; :mod:`runner.stage`, "Lifecycle and threads").
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any, TypeVar

from runner.broadcast import unbounded
from runner.stage import Context, Stage

T = TypeVar("T")


def lifecycle_context(stage: Stage, *, device: str) -> Context:
    """The :class:`Context` handed to ``open`` and ``close``: the device and the stage's logger;
    no folder to write in (files are written by ``run`` / ``process`` only)."""

    def files_dir(port: str) -> Path:
        raise RuntimeError(f"{stage.name}: ctx.files_dir({port!r}) is for run/process, not open/close")

    return Context(device=device, files_dir=files_dir, log=logging.getLogger(f"runner.stage.{stage.name}"))


class Lifecycle:
    """One stage instance of a run. :meth:`call` opens it on the first call (once, other threads
    waiting meanwhile) and, for a ``"single"`` stage, holds the instance's lock around each call,
    inside :func:`runner.broadcast.unbounded` so that a thread holding it never waits for a
    slower reader of a stream (that reader may wait for this lock). :meth:`close` closes it if
    it was opened. Thread-safe."""

    def __init__(self, stage: Stage, *, device: str):
        self.stage = stage
        self._device = device
        self._opening = threading.Lock()
        self._opened = False
        self._single = threading.Lock() if stage.threading == "single" else None

    @property
    def opened(self) -> bool:
        return self._opened

    def call(self, inputs: Mapping[str, Any], params: Mapping[str, Any], compute: Callable[[], T]) -> T:
        """``compute()`` (a ``run`` or ``process`` of the stage with these ``inputs`` and
        ``params``), the stage opened first if it is not."""
        with self._opening:
            if not self._opened:
                self.stage.open(inputs, params, lifecycle_context(self.stage, device=self._device))
                self._opened = True
        if self._single is None:
            return compute()
        with unbounded(), self._single:
            return compute()

    def close(self) -> None:
        """Close the stage if it was opened (once); call when no call is running any more."""
        with self._opening:
            if self._opened:
                self._opened = False
                self.stage.close(lifecycle_context(self.stage, device=self._device))


@contextlib.contextmanager
def opened(stage: Stage, inputs: Mapping[str, Any], params: Mapping[str, Any], *, device: str = "cpu") -> Iterator[Lifecycle]:
    """A stage opened with ``inputs`` and ``params`` for calls outside a run (tests, scripts),
    closed on leaving: ``with opened(stage, inputs, params) as life: life.call(inputs, params,
    lambda: stage.process(...))``, or ``stage.process(...)`` directly (calls not serialized)."""
    life = Lifecycle(stage, device=device)
    try:
        life.call(inputs, params, lambda: None)
        yield life
    finally:
        life.close()
