"""Warnings a stage gives while it computes an entry, kept with the entry and given again when a
later run takes the entry from the cache.

A stage warns through ``ctx.log`` (a logger under ``runner.stage``); the Python warnings of the
libraries it calls (numpy's ``RuntimeWarning``...) reach the same loggers as one line each
(:func:`one_line_warnings`). While the runner computes an entry it collects the warning lines
logged on its thread (:func:`recording`) and stores them in the entry's completion record
(``warnings``); a run that takes the entry from the cache logs them again (:meth:`Replay.entry`,
each line once per stage and run), so a cached rerun of a shot whose reference frame is poor
says so as the run that computed it did. During a run each distinct line reaches stderr once
(:func:`showing`): a stage computed in a child process and looked up by the run said it once.
"""

from __future__ import annotations

import logging
import sys
import threading
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import Any

from runner.stage import SUMMARY

STAGE_LOGGER = "runner.stage"
MAX_LINE = 400  # characters of a warning line (a longer one is cut, saying how much was left out)

_recorder: ContextVar[list[str] | None] = ContextVar("runner_notes", default=None)
_shown: set[str] | None = None  # lines shown during the run in progress (:func:`showing`)
_shown_lock = threading.Lock()


class _StageWarnings(logging.Handler):
    """The warning lines of the ``runner.stage`` loggers: appended to this thread's recording,
    and written to stderr, each once while a run goes on (:func:`showing`), unless the
    application has its own logging handlers (an editor, pytest), which then show them: as
    Python's last-resort handler does where no handler is installed."""

    def emit(self, record: logging.LogRecord) -> None:
        line = bounded(record.getMessage())
        lines = _recorder.get()
        if lines is not None and line not in lines:
            lines.append(line)
        if self._others(record):
            return
        with _shown_lock:
            if _shown is not None:
                if line in _shown:
                    return
                _shown.add(line)
        sys.stderr.write(line + "\n")
        sys.stderr.flush()

    def _others(self, record: logging.LogRecord) -> bool:
        """Whether another handler on ``record``'s way to the root logger takes it."""
        logger: logging.Logger | None = logging.getLogger(record.name)
        while logger is not None:
            if any(handler is not self and record.levelno >= handler.level for handler in logger.handlers):
                return True
            logger = logger.parent if logger.propagate else None
        return False


logging.getLogger(STAGE_LOGGER).addHandler(_StageWarnings(SUMMARY))
logging.getLogger(STAGE_LOGGER).setLevel(logging.INFO)  # SUMMARY lines are made (the root's WARNING would drop them)


@contextmanager
def showing() -> Iterator[None]:
    """While the block runs (one run), each distinct warning line is written once."""
    global _shown
    with _shown_lock:
        outer, _shown = _shown, set()
    try:
        yield
    finally:
        with _shown_lock:
            _shown = outer


@contextmanager
def recording() -> Iterator[list[str]]:
    """Collect the warning lines logged on this thread while the block runs (each once)."""
    lines: list[str] = []
    token = _recorder.set(lines)
    try:
        yield lines
    finally:
        _recorder.reset(token)


class Replay:
    """Gives again the warnings recorded in entries taken from the cache, each line once per
    stage and run."""

    def __init__(self) -> None:
        self._given: set[tuple[str, str]] = set()
        self._lock = threading.Lock()

    def entry(self, stage: str, record: dict[str, Any]) -> None:
        """Log the ``warnings`` of the completion record ``record`` of ``stage``'s entry."""
        for line in record.get("warnings", ()):
            with self._lock:
                if (stage, line) in self._given:
                    continue
                self._given.add((stage, line))
            logging.getLogger(f"{STAGE_LOGGER}.{stage}").warning("%s", line)


def bounded(line: str) -> str:
    """``line`` on one line, cut at :data:`MAX_LINE` characters."""
    line = " ".join(line.split())
    if len(line) <= MAX_LINE:
        return line
    return f"{line[:MAX_LINE]}... ({len(line) - MAX_LINE} more characters)"


def _as_log_line(
    message: Warning | str, category: type[Warning], filename: str, lineno: int, file: Any = None, line: str | None = None
) -> None:
    """:func:`warnings.showwarning` as one ``warning:`` line on the ``runner.stage`` logger,
    naming the warning's kind and where it was raised (the library's file)."""
    where = Path(filename)
    short = "/".join(where.parts[-2:]) if len(where.parts) >= 2 else filename
    logging.getLogger(STAGE_LOGGER).warning("%s", bounded(f"warning: {message} ({category.__name__}, {short}:{lineno})"))


def one_line_warnings() -> None:
    """Show every Python warning of this process as one line of the tool's own on the
    ``runner.stage`` logger (recorded with an entry being computed, relayed by a child
    process), instead of Python's two lines with the library's source line."""
    warnings.showwarning = _as_log_line
