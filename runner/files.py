"""Files the tool reads: regular files of bounded size, checked before they are opened.

A path given by a user may name a character device (``/dev/zero``: endless bytes), a FIFO (an
``open`` that waits for a writer forever), a socket or a folder, directly or through a symlink.
:func:`kind_problem` says what such a path is from its ``stat`` alone, never opening it;
:func:`open_regular` opens a file only once it is a regular file (without blocking, checked
again on the open descriptor), and :func:`read_limited` reads one whole only up to a size.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path
from typing import BinaryIO

_KINDS = (
    (stat.S_ISDIR, "a folder, not a file"),
    (stat.S_ISCHR, "a character device, not a regular file"),
    (stat.S_ISBLK, "a block device, not a regular file"),
    (stat.S_ISFIFO, "a FIFO (named pipe), not a regular file"),
    (stat.S_ISSOCK, "a socket, not a regular file"),
)


def describe_mode(mode: int) -> str | None:
    """What a file of ``st_mode`` ``mode`` is when it is not a regular file, or None."""
    if stat.S_ISREG(mode):
        return None
    return next((text for test, text in _KINDS if test(mode)), "not a regular file")


def kind_problem(path: str | Path) -> str | None:
    """Why ``path`` (symlinks followed) is not a regular file: ``"no such file"``, ``"a folder,
    not a file"``, ``"a FIFO (named pipe), not a regular file"``...; None for a regular file."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "no such file"
    except OSError as exc:
        return f"cannot read ({exc.strerror or exc})"
    return describe_mode(mode)


def open_regular(path: str | Path) -> BinaryIO:
    """``path`` opened for reading in binary, once it is a regular file.

    Raises
    ------
    OSError
        ``path`` is missing or is not a regular file (``strerror`` says what it is: a FIFO, a
        character device...); ``filename`` is ``path``.
    """
    problem = kind_problem(path)
    if problem == "no such file":
        raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), str(path))
    if problem:
        raise OSError(errno.EINVAL, problem, str(path))
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # a FIFO swapped in since the stat does not block
    try:
        problem = describe_mode(os.fstat(fd).st_mode)
        if problem:
            raise OSError(errno.EINVAL, problem, str(path))
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_limited(path: str | Path, limit: int) -> bytes:
    """The bytes of regular file ``path``, at most ``limit`` of them.

    Raises
    ------
    OSError
        As :func:`open_regular`, or the file holds more than ``limit`` bytes (``EFBIG``).
    """
    with open_regular(path) as f:
        data = f.read(limit + 1)
    if len(data) > limit:
        raise OSError(errno.EFBIG, f"larger than the {limit} bytes such a file may have", str(path))
    return data
