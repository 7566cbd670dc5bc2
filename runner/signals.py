"""Interrupts and the process's end: exit codes, SIGINT/SIGTERM handling, :func:`exit_now`.

A module of its own, below everything else in the runner, so that the command line
(:mod:`runner.cli`), the child processes of :mod:`runner.offload` and the run itself share one
flag and one way to end without importing each other.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
from typing import NoReturn

EXIT_OK, EXIT_STAGE, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130

#: Set by the first SIGINT / SIGTERM (:func:`interrupt`); the run stops at its next event.
INTERRUPTED = threading.Event()


def interrupt(signum: int, frame: object) -> None:
    """SIGINT / SIGTERM: interrupt the run. The flag is kept because the KeyboardInterrupt raised
    here can be swallowed when the signal lands inside a C callback (a codec's); the run then stops
    at its next event (a chunk, a stage), still exit 130. A second signal ends the process at once
    (exit 130), for a run whose stop waits on work that does not end: what it committed stays,
    its locks are broken by the next run (the cache's commits are atomic)."""
    if INTERRUPTED.is_set():
        try:
            os.write(2, b"interrupted again: exiting now\n")
        except OSError:  # a closed stderr (a pipe whose reader the first Ctrl-C ended)
            pass
        finally:
            os._exit(EXIT_INTERRUPTED)
    INTERRUPTED.set()
    raise KeyboardInterrupt


def unraisable(args: sys.UnraisableHookArgs) -> None:
    """A KeyboardInterrupt swallowed in a callback (an import lock's, a codec's) is not reported
    as "Exception ignored": :data:`INTERRUPTED` carries it to the next event."""
    if not issubclass(args.exc_type, KeyboardInterrupt):
        sys.__unraisablehook__(args)


def install() -> None:
    """Make SIGINT and SIGTERM both interrupt the run (:func:`interrupt`). SIGINT is set
    explicitly: a process started in the background of a non-interactive shell inherits it
    ignored, and Python then keeps ignoring it."""
    signal.signal(signal.SIGTERM, interrupt)
    signal.signal(signal.SIGINT, interrupt)
    sys.unraisablehook = unraisable


def exit_now(code: int) -> NoReturn:
    """End the process with exit status ``code`` once its own threads have finished and its
    output is flushed, skipping the interpreter's teardown: unloading torch, OpenCV and
    matplotlib module by module took 1.0-1.3 s after every run that synthesized (0.2 s without
    torch), and it writes nothing. Everything the command writes is already closed (the cache's
    entries and ``--out`` are committed by atomic renames before this point)."""
    for thread in threading.enumerate():
        if thread is not threading.current_thread() and not thread.daemon:
            thread.join()
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
