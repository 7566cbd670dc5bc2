"""Pipeline inputs as a run reads them: their digests, and the check that they did not change.

A pipeline input (a clip, another file, a folder such as an actor pack or a folder of photos)
enters every key below it through its digest (:func:`runner.digest.input_digest`), taken once
when the run starts. Stages read the input later, chunk by chunk, so a file replaced (renamed
over), rewritten or touched while the run goes on would be read with new bytes under the old
digest, and the results stored under keys that say they came from the old bytes.

So each input keeps the stat record of every file in it (:func:`stat_record`: size, mtime and
ctime in ns, inode, device; a renamed file keeps its mtime but gets a new ctime), taken before
and after its digest (a file written while it was hashed is hashed again), and the runner calls
:meth:`Inputs.check` before it commits any entry computed from an input: a record that differs
(a file replaced, rewritten, touched, added or removed) fails the stage with one line, and
nothing is stored under the old digest. The reads of a committed entry all happened before its
check, while the records still held, so they read the bytes the digest describes.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from runner.config import Pipeline
from runner.digest import input_digest, tree_files
from runner.stage import StageError

HASH_ATTEMPTS = 3  # digests taken again while an input keeps changing under them


class InputChanged(StageError):
    """An input's files changed after its digest was taken."""


def stat_record(kind: str, path: Path) -> dict[str, tuple[int, ...] | None]:
    """Per file of input ``path`` (``kind`` ``dir``: every file under it, by relative path;
    else the file itself, as ``"."``), ``(size, mtime_ns, ctime_ns, inode, device)``; None for a
    file that cannot be stat'ed."""
    files = [(p.relative_to(path).as_posix(), p) for p in tree_files(path)] if kind == "dir" else [(".", path)]
    record: dict[str, tuple[int, ...] | None] = {}
    for name, file in files:
        try:
            st = os.stat(file)
        except OSError:
            record[name] = None
            continue
        record[name] = (st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino, st.st_dev)
    return record


@dataclass(frozen=True)
class BoundInput:
    """One pipeline input: ``name``, ``kind`` (video, file, dir), ``path``, its ``digest`` and
    the :func:`stat_record` its digest was taken under."""

    name: str
    kind: str
    path: Path
    digest: str
    record: dict[str, tuple[int, ...] | None]

    @classmethod
    def read(cls, name: str, kind: str, path: Path) -> BoundInput:
        """Hash input ``path``; again while its stat record changes during the hashing.

        Raises
        ------
        InputChanged
            It changed during each of :data:`HASH_ATTEMPTS` attempts.
        """
        path = Path(path)
        for _ in range(HASH_ATTEMPTS):
            before = stat_record(kind, path)
            digest = input_digest(kind, path)
            if stat_record(kind, path) == before:
                return cls(name, kind, path, digest, before)
        raise InputChanged(f"input {name!r} ({path}): its files kept changing while they were hashed")

    def changed(self) -> str | None:
        """The first file of this input whose stat record differs from the one its digest was
        taken under (``"."``: the input itself), or None."""
        now = stat_record(self.kind, self.path)
        return next((name for name in sorted(set(now) | set(self.record)) if now.get(name) != self.record.get(name)), None)


class Inputs:
    """The bound inputs of one run, and which of them each stage's results come from."""

    def __init__(self, pipeline: Pipeline, bound: dict[str, Path]):
        self.bound = {name: BoundInput.read(name, pipeline.inputs[name].type, path) for name, path in bound.items()}
        self._pipeline = pipeline
        self._reads: dict[str, list[BoundInput]] = {}

    def digest(self, name: str) -> str:
        return self.bound[name].digest

    def check(self, stage: str) -> None:
        """Raise :class:`InputChanged` if an input that ``stage`` or a stage above it reads has
        changed since its digest was taken (call it before committing an entry of ``stage``)."""
        if stage not in self._reads:
            names = {
                ref.port
                for up in self._pipeline.ancestors(stage)
                for ref in self._pipeline.stages[up].inputs.values()
                if ref.stage is None
            }
            self._reads[stage] = [self.bound[name] for name in sorted(names) if name in self.bound]
        for bound in self._reads[stage]:
            file = bound.changed()
            if file is not None:
                where = bound.path if file == "." else bound.path / file
                raise InputChanged(
                    f"input {bound.name!r} changed while the run read it ({where} was replaced, "
                    f"written, added or removed since its digest was taken); nothing computed from it "
                    f"since was stored: run again once it stays unchanged"
                )
