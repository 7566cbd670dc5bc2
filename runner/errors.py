"""A stage's failure as the user sees it: one line naming the stage (exit code 1)."""

from __future__ import annotations

import contextlib
import errno
from collections.abc import Iterator

from runner.config import StageNode
from runner.stage import StageError

_DISK_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO)


class StageFailed(Exception):
    """A stage raised :class:`StageError`; the message names the stage."""

    def __init__(self, node: StageNode, error: StageError):
        self.node = node
        message = str(error)
        for prefix in (f"{node.uses}: ", f"{node.name}: "):  # a stage that names itself: once
            message = message.removeprefix(prefix)
        super().__init__(f"stage {node.name!r} ({node.uses}): {message}")


@contextlib.contextmanager
def stage_errors(node: StageNode) -> Iterator[None]:
    """Turn a :class:`StageError`, or an :class:`OSError` of a full or failing disk, raised
    while ``node`` runs, is stored or is published into :class:`StageFailed` naming the stage
    (and the file)."""
    try:
        yield
    except StageError as exc:
        raise StageFailed(node, exc) from exc
    except OSError as exc:
        if exc.errno not in _DISK_ERRORS:
            raise
        where = f"{exc.filename}: " if exc.filename else ""
        raise StageFailed(node, StageError(f"{where}{exc.strerror or exc}")) from exc
