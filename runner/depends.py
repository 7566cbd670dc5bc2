"""Files a stage's result depends on beyond its inputs and parameters, recorded while it runs.

A loader that reads a file named indirectly (a layout named by a pack manifest or a parameter,
resolved to a bundled YAML file) calls :func:`depends_on` with the path. While the runner computes
an entry it collects these paths (:func:`recording`) and stores each file's sha256 in the entry's
completion record; before the entry is used again the runner hashes the files again, and a
changed or missing file makes the entry stale (recomputed). Outside a run :func:`depends_on`
does nothing. The runner knows nothing about what the files mean.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path

_recorder: ContextVar[set[Path] | None] = ContextVar("runner_depends", default=None)


def depends_on(path: str | Path) -> None:
    """Record that the result being computed depends on the bytes of file ``path``."""
    files = _recorder.get()
    if files is not None:
        files.add(Path(path).resolve())


@contextmanager
def recording(into: set[Path]) -> Iterator[set[Path]]:
    """Collect into ``into`` the paths passed to :func:`depends_on` in this thread while the
    block runs."""
    token = _recorder.set(into)
    try:
        yield into
    finally:
        _recorder.reset(token)


@contextmanager
def not_recording() -> Iterator[None]:
    """Files read while the block runs are not dependencies: a stage re-reading what it has
    just written (to check it) must not make its entry depend on its own temporary output."""
    token = _recorder.set(None)
    try:
        yield
    finally:
        _recorder.reset(token)
