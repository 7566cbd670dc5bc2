"""Atomic file creation: write under a temporary name in the same folder, then ``os.replace``."""

from __future__ import annotations

import os
import secrets
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator


def temp_name(final: Path) -> Path:
    """A hidden temporary sibling of ``final`` that never matches its name pattern.

    ``frame.000012.exr`` -> ``.frame.000012.exr.<8 hex>.part``: the leading dot and the ``.part``
    suffix keep it out of globs like ``frame.*.exr``; the random part lets writers run side by side.
    """
    return final.with_name(f".{final.name}.{secrets.token_hex(4)}.part")


@contextmanager
def atomic_write(final: Path) -> Iterator[Path]:
    """Yield a temporary path to write; on success rename it to ``final`` in one step.

    If the body raises, the temporary file is removed and ``final`` is left as it was (absent, or
    the previous complete file). A process killed inside the body leaves at most a ``.part`` file,
    never a partial ``final``. The rename is atomic on one file system (same folder), which makes
    this safe against process death; it does not fsync, so it is not a guarantee against power loss.
    """
    tmp = temp_name(final)
    try:
        yield tmp
        os.replace(tmp, final)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
