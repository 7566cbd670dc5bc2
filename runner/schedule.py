"""The streaming executor's schedule: which stage runs when, on which thread or process.

:class:`StreamingSchedule` visits every selected stage of a :class:`runner.execute.Runner` once
the stages it reads have had their turn: in topological order on the scheduling thread, except

- a stage that reads a stream being computed (:meth:`runner.execute.Runner._stream_reads`),
  which runs on a thread of its own, at the same time as the other readers of that stream, so
  that each chunk is computed once and handed to all (:meth:`launch`);
- with ``Options.offload``, a stage reading a source's frames and its branch of sequence stages,
  which run in a child process while the scheduling thread keeps busy (:meth:`offload`,
  :mod:`runner.offload`); the run then finds their entries in the cache.

While it only waits, the scheduling thread imports the modules the waiting stages declare
(:meth:`import_ahead`). The first failure stops new stages; it is raised once the running ones
have ended. The serial executor (:mod:`runner.serial`) has none of this: one stage at a time.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from runner.chunks import input_digests, is_source
from runner.config import StageNode
from runner.digest import cache_key
from runner.offload import Forked
from runner.offload import fork as offload_fork
from runner.offload import spec as offload_spec
from runner.offload import start as offload_start
from runner.progress import Report
from runner.stage import FrameStage

if TYPE_CHECKING:
    from runner.execute import Runner

IMPORT_POLL_S = 0.05  # how often the scheduling thread looks whether a stream computes (imports ahead)

_IN_CHILD = object()  # put on `ended` when a child process ends

Ended = tuple[StageNode, Any, BaseException | None]  # a stage's report (None: lazy; _IN_CHILD) or failure


class StreamingSchedule:
    """One run's schedule: the stages ``waiting``, ``done``, ``running`` on threads, and those
    given to ``children`` (a stage's name -> the child process computing it)."""

    def __init__(self, run: Runner, emit: Callable[[Report], None]):
        self.run, self.emit = run, emit
        self.waiting = run.selected()
        self.done: set[str] = set()
        self.running: dict[str, threading.Thread] = {}
        self.ended: queue.Queue[Ended] = queue.Queue()
        self.children: dict[str, Any] = {}
        self.offered: set[str] = set()  # stages given to a child process, once each
        self.imported: set[str] = set()  # modules imported ahead
        self.failure: BaseException | None = None

    def schedule(self) -> None:
        """Visit every stage; raises the first failure once the running stages have ended."""
        try:
            while self.waiting or self.running or self.children:
                ready = [] if self.failure is not None else self._ready()
                setups = [node for node in ready if self.run._sets_up_only(node)]
                if ready and not setups and (self.launch(ready) or self.offload(ready)):
                    continue
                if ready:
                    node = (setups or ready)[0]
                    self.waiting.remove(node)
                    ended: Ended | None = self._visit(node)
                elif self.running or self.children:
                    ended = self._wait()
                else:
                    break
                if ended is not None:
                    self._finish(*ended)
        except BaseException:  # interrupted: the stages on threads stop at their next event
            self.run._stopping.set()
            for child in set(self.children.values()):
                child.terminate()
                child.wait()
            for thread in self.running.values():
                thread.join()
            raise
        if self.failure is not None:
            raise self.failure

    def _wait(self) -> Ended | None:
        """Import ahead, then wait for a stage on a thread or a child process to end: the stage
        that ended, or None for a child process (its stages are then visited: their entries are
        in the cache)."""
        self.import_ahead()
        node, report, error = self.ended.get()
        if report is _IN_CHILD:
            child = self.children[node.name]
            for name in [name for name, c in self.children.items() if c is child]:
                self.children.pop(name)
            return None
        self.running.pop(node.name)
        return node, report, error

    def _finish(self, node: StageNode, report: Report | None, error: BaseException | None) -> None:
        """A stage has had its turn: report it (None: a lazy frame stage, reported once
        resolved) and the lazy frame stages now resolved; keep the first failure."""
        self.done.add(node.name)
        self.failure = self.failure or error
        for finished in self.run._finished_lazy():
            self.emit(finished)
        if report is not None:
            self.emit(report)

    def _ready(self) -> list[StageNode]:
        """The waiting stages not given to a child whose inputs have all had their turn."""
        return [
            node
            for node in self.waiting
            if node.name not in self.children and all(ref.stage is None or ref.stage in self.done for ref in node.inputs.values())
        ]

    def _visit(self, node: StageNode) -> Ended:
        try:
            return node, self.run._visit(node), None
        except BaseException as exc:  # noqa: BLE001 - re-raised on the scheduling thread
            return node, None, exc
        finally:
            self.run._leave(node)

    # -- stages on threads -----------------------------------------------------------------

    def launch(self, ready: list[StageNode]) -> bool:
        """Start every ready stage that reads a stream being computed, each registered with the
        broadcasts it reads before any starts (so none finds a chunk dropped). Whether any started."""
        run, started = self.run, []
        for node in ready:
            threaded, joins = run._stream_reads(node)
            if threaded:
                thread = threading.Thread(
                    target=lambda n=node: self.ended.put(self._visit(n)), name=f"stage-{node.name}", daemon=True
                )
                for chunks, reader in joins:
                    chunks.broadcast.join(reader, thread)
                run._joined[node.name] = [(chunks, reader, thread) for chunks, reader in joins]
                self.running[node.name] = thread
                self.waiting.remove(node)
                started.append(thread)
        producers = list(dict.fromkeys(chunks for name in run._joined for chunks, _, _ in run._joined[name]))
        for chunks in producers:
            chunks.produce()
        run._producers.update(dict.fromkeys(producers))
        for thread in started:
            thread.start()
        return bool(started)

    def import_ahead(self) -> None:
        """Import the modules the waiting stages declare (:attr:`runner.stage.Stage.imports`),
        once each, while this thread would only wait for a streamed section that computes: once
        a streamed stage has computed a chunk in this run (a cached run, whose streams are only
        looked up, would be held up by imports its cached stages never use). Returns when they
        are imported, the streams are all resolved, or a stage has ended. A module that fails to
        import is left to the stage, which reports it when it runs."""
        modules = [m for node in self.waiting for m in node.cls.imports if m not in self.imported]
        streams = list(self.run._producers)
        while modules and streams and self.ended.empty():
            if any(chunks.computed(i) for chunks in streams for i in range(len(chunks.ranges))):
                for module in dict.fromkeys(modules):
                    self.imported.add(module)
                    with contextlib.suppress(Exception):
                        importlib.import_module(module)
                return
            if all(chunks.complete() for chunks in streams):
                return
            time.sleep(IMPORT_POLL_S)

    # -- child processes -------------------------------------------------------------------

    def offload(self, ready: list[StageNode]) -> bool:
        """Start a child process for a stage that reads a source's frames, the sequence stages
        it waits for, and the sequence stages after it that read nothing else still to compute,
        when a ready stage outside them keeps this thread busy meanwhile (at most one child per
        spare core). Whether one started."""
        run = self.run
        if not run.opts.offload or len(set(self.children.values())) >= run.services.producers - 1:
            return False
        choices = (
            (n, self._offload_stages(n)) for n in self.waiting if n.name not in self.offered and n.name not in self.children
        )
        node, stages = next(((n, s) for n, s in choices if s and any(r.name not in s for r in ready)), (None, []))
        if node is None:
            return False
        self.offered.update(stages)  # once: after a failed child, the run computes them
        child: Any = offload_fork(lambda **events: run.child_runner(stages, **events))
        if child is None:
            child = offload_start(
                offload_spec(
                    pipeline=run.pipeline.path,
                    overrides=list(run.opts.overrides),
                    bound=run._bound,
                    cache=run.store.root,
                    device=run.opts.device,
                    stages=stages,
                )
            )
        self.children.update(dict.fromkeys(stages, child))
        threading.Thread(target=lambda: self._relay_until_ended(node, child), daemon=True, name=f"child-{node.name}").start()
        run.log(
            {
                "event": "offload",
                "stage": node.name,
                "stages": stages,
                "pid": child.pid,
                "started": "fork" if isinstance(child, Forked) else "interpreter",
            }
        )
        return True

    def _relay_until_ended(self, node: StageNode, child: Any) -> None:
        try:
            self._relay(child)
        finally:
            child.wait()
            self.ended.put((node, _IN_CHILD, None))

    def _relay(self, child: Any) -> None:
        """Read a child process's events (one JSON object a line on its standard output, text)
        until it ends: each is logged as a ``child`` event, a warning is shown, a stage's log
        record is logged again on its logger, and the seconds of a stage it ran are kept for that
        stage's report."""
        run = self.run
        for line in child.stdout:
            try:
                event = json.loads(line)
            except ValueError:
                continue
            if event.get("event") == "warning":
                run.opts.warn(event.get("line", ""))
            if event.get("event") == "log":
                logging.getLogger(event.get("logger", "runner.stage")).log(
                    event.get("level", logging.WARNING), "%s", event.get("message", "")
                )
            if event.get("event") == "stage" and event.get("status") == "ran":
                run._in_child[event["stage"]] = (event.get("seconds", 0.0), event.get("cpu_seconds", 0.0))
            try:
                run.log({"event": "child", "pid": child.pid, "child": event})
            except KeyboardInterrupt:  # the run is stopping: it terminates the child
                break

    def _offload_stages(self, node: StageNode) -> list[str]:
        """What a child process computes for ``node`` (:meth:`_offloadable`), in order: the
        stages ``node`` still waits for (sequence stages, not forced: e.g. the performer's pack),
        ``node``, and the waiting sequence stages after it (not forced) that read it or each other
        and otherwise only pipeline inputs and stages done (the performer's branch; the run
        keeps the rest). Empty when ``node`` is not for a child, waits for a frame stage, or waits
        for a stage whose entry is stored (a cached run visits it at once, then looks ``node`` up)."""
        if not self._offloadable(node):
            return []
        stages_of = self.run.pipeline.stages
        waiting_names = {other.name for other in self.waiting}
        before = self.run.pipeline.ancestors(node.name) & waiting_names - {node.name}
        if any(not self._child_may_run(stages_of[name]) or self._stored(stages_of[name]) for name in before):
            return []  # e.g. a stage it waits for is found in the cache: decide once it is visited
        stages = [other.name for other in self.waiting if other.name in before] + [node.name]
        grown = True
        while grown:
            grown = False
            for other in self.waiting:
                if (
                    other.name not in stages
                    and self._child_may_run(other)
                    and any(ref.stage in stages for ref in other.inputs.values())
                    and all(ref.stage is None or ref.stage in self.done or ref.stage in stages for ref in other.inputs.values())
                ):
                    stages.append(other.name)
                    grown = True
        return stages

    def _offloadable(self, node: StageNode) -> bool:
        """Whether ``node`` may run in a child process: a sequence stage, not forced, reading the
        frames of a source that is set up (an uncached frame stage that reads no frames:
        decoding, done), whose entry is not known to be stored."""
        if not self._child_may_run(node):
            return False
        stages_of = self.run.pipeline.stages
        if not any(ref.stage in self.done and is_source(stages_of[ref.stage].cls) for ref in node.inputs.values()):
            return False
        return not self._stored(node)

    def _child_may_run(self, node: StageNode) -> bool:
        """A sequence stage, not forced: one a child process may compute."""
        return not issubclass(node.cls, FrameStage) and node.name not in self.run.opts.force

    def _stored(self, node: StageNode) -> bool | None:
        """Whether ``node``'s entry is in the cache; None while its inputs are not all computed
        (stages not done, or digests known only once computed)."""
        if any(ref.stage is not None and ref.stage not in self.done for ref in node.inputs.values()):
            return None
        inputs = self.run._inputs(node)
        if any(v.known_digest() is None for v in inputs.values()):
            return None
        keys = self.run.keys
        return keys.lookup(node, cache_key(keys.material(node, input_digests(inputs)))) is not None
