"""What a run tells its user while it goes: per-stage reports, chunk and warning events,
progress bars (each stage's own time: :mod:`runner.timing`)."""

from __future__ import annotations

import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from runner.config import StageNode
from runner.notes import Replay
from runner.outputs import Damaged

if TYPE_CHECKING:
    from tqdm import tqdm


@dataclass
class Report:
    """One stage's outcome: ``status`` is cached / ran / partial / on demand (run) or
    cached / will run / may run / on demand (dry run)."""

    stage: str
    uses: str
    status: str
    reason: str = ""
    chunks: int | None = None
    chunks_cached: int = 0
    frames: int | None = None
    seconds: float = 0.0
    cpu_seconds: float = 0.0  # of the stage's own Python thread(s), see own_time

    def line(self) -> str:
        parts = [f"{self.stage:<14} {self.uses:<18} {self.status:<9}"]
        if self.chunks is not None:
            parts.append(f"{self.chunks_cached}/{self.chunks} chunks cached")
        if self.frames is not None:
            parts.append(f"{self.frames} frames")
        if self.status in ("cached", "ran", "partial"):
            parts.append(f"{self.seconds:.2f} s")
        if self.reason:
            parts.append(f"({self.reason})")
        return "  ".join(parts)


class Progress:
    """Events (``log``, one JSON-able dict each), warning lines (``warn``), progress bars on
    stderr (``bars``), and ``current``: the stage whose turn it is on the calling thread
    (stages reading one stream run on threads of their own)."""

    def __init__(self, *, log: Callable[[dict[str, Any]], None], warn: Callable[[str], None], bars: bool):
        self.log, self.warn, self.bars = log, warn, bars
        self._turn = threading.local()
        self._lock = threading.Lock()
        self._nondeterministic: set[str] = set()  # stages warned about (:meth:`nondeterministic`)
        self.replay = Replay().entry  # (stage, completion record): its recorded warnings, once each

    @property
    def current(self) -> str | None:
        return getattr(self._turn, "stage", None)

    @current.setter
    def current(self, stage: str | None) -> None:
        self._turn.stage = stage

    def bar(self, node: StageNode, total: int | None) -> tqdm:
        from tqdm import tqdm  # here: importing it costs start-up time

        tqdm.monitor_interval = 0  # no monitor thread: the run forks child processes (runner.offload)
        return tqdm(
            total=total, desc=node.name, unit="frame", file=sys.stderr, leave=False, disable=not self.bars, dynamic_ncols=True
        )

    def waiting(self, node: StageNode) -> Callable[[dict[str, Any]], None]:
        """``on_wait`` for :meth:`runner.cache.CacheStore.locked`: a ``wait`` event."""

        def on_wait(holder: dict[str, Any]) -> None:
            self.log({"event": "wait", "stage": node.name, "holder_pid": holder.get("pid")})

        return on_wait

    def damaged(self, node: StageNode, exc: Damaged) -> None:
        """A damaged cache file (one line on stderr, a ``damaged`` event); its entry is
        recomputed by the caller."""
        self.warn(f"warning: stage {node.name!r}: damaged cache entry ({exc}); recomputing it")
        self.log({"event": "damaged", "stage": node.name, "file": str(exc.path)})

    def nondeterministic(self, node: StageNode, start: int, stop: int, ports: list[str]) -> None:
        """Frames computed again that differ from their entry's recorded digest: a
        ``nondeterministic`` event each time, one warning line per stage."""
        self.log({"event": "nondeterministic", "stage": node.name, "start": start, "stop": stop, "ports": ports})
        with self._lock:
            first = node.name not in self._nondeterministic
            self._nondeterministic.add(node.name)
        if first:
            self.warn(
                f"warning: stage {node.name!r} computed frames {start}-{stop - 1} again and they differ from "
                f"those its cache entry recorded ({', '.join(ports)}): the stage is not deterministic, so "
                f"outputs of this resumed run may differ from an uninterrupted run's "
                f"(`--force {node.name}` computes it again, and what reads it follows its new frames)"
            )
