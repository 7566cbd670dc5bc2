"""The serial executor: the reference semantics of a run, which the streaming executor
(:class:`runner.execute.Runner`) must match byte for byte.

Stages run one at a time on the calling thread, in the order of :func:`runner.plan.visit_order`:
a frame stage resolves its chunks in order at its turn (computing and committing the missing
ones, one at a time whatever ``--jobs``), a sequence stage runs once its inputs are whole. No
stage runs on a thread of its own, no frames are handed from one stage to the next as they are
computed (a reader gets a cached stage's frames computed again, as a later run would), no
producer or read-ahead thread, no child process. Entries are computed, stored and committed by
the same code as in the streaming run, so both store the same entries under the same keys;
stages are opened and closed as there (:mod:`runner.lifecycle`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

from runner.execute import Runner
from runner.plan import visit_order
from runner.progress import Report


class SerialExecutor(Runner):
    """Runs one pipeline with bound inputs serially; :meth:`run` returns one :class:`Report` per stage."""

    streaming: ClassVar[bool] = False

    def _schedule(self, emit: Callable[[Report], None]) -> None:
        """Visit every selected stage in turn; the first failure stops the run."""
        for node in visit_order(self.selected()):
            report = self._visit(node)
            if report is not None:  # a frame stage is never lazy here: always a report
                emit(report)
