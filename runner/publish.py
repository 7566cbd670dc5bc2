"""Publishing ``files`` outputs to ``--out/<stage>/``: whole or absent, verified, never over a
user's files, never sharing bytes with the cache.

A stage's folder is built as ``--out/.<stage>.<pid>.tmp`` (holding a marker, :data:`MARKER`,
that names this tool, the stage, the process and its host), each file hashed and compared with
the sha256 its cache entry recorded as it is copied from the entry (a copy-on-write clone,
hashed, where the filesystem makes one: :func:`runner.outputs.copy_verified`), and
``manifest.json`` (the file list with sizes and sha256, and the entries' keys) written last;
then the old folder is moved to ``.<stage>.<pid>.old`` (marked
too), the new one into place, and the old one deleted, its marker last.

What may be replaced: only a folder whose ``manifest.json`` names this tool and this stage and
lists every file in it, i.e. what an earlier publish wrote. Anything else at ``--out/<stage>``
(a user's folder or file that happens to have a stage's name, a file added inside a published
folder) is reported by :func:`conflicts` before anything runs. Leftover ``.<stage>.<pid>.tmp``
and ``.old`` folders of processes of this host that are gone (a kill between the two renames)
are removed by :func:`remove_leftovers`, which every run and ``runner cache gc --out`` call:
only those this tool's publish wrote, as their marker (or, for an ``.old`` folder, its
manifest) proves; any other folder with such a name is left alone.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
import socket
import tempfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from runner.cache import Entry, holder_is_stale
from runner.outputs import Damaged, copy_verified, file_stat, output_path
from runner.stage import StageError

MANIFEST = "manifest.json"
MARKER = ".runner-publish.json"  # in a temporary or replaced folder: the run of this tool that made it
TOOL = "expression-mapping runner"
# The project's own folders (beside ``runner/``): an --out there would mix outputs with its files.
PROJECT_FOLDERS = ("runner", "stages", "editor", "lab", "scripts", "tests", "fixtures", "docs", "benchmarks")
_LEFTOVER = re.compile(r"^\.(?P<stage>[A-Za-z0-9_-]+)\.(?P<pid>\d+)\.(tmp|old)$")


@dataclass
class Published:
    """What one stage publishes: its ``files`` ports and the entries holding them (one for a
    sequence stage, one per chunk for a frame stage); ``redo(i)`` recomputes entry ``i`` after
    it was found damaged and returns the new entry."""

    stage: str
    uses: str
    ports: list[str]
    entries: list[Entry]
    redo: Callable[[int], Entry]


def conflicts(out: Path, stages: Iterable[str]) -> list[tuple[Path, str]]:
    """Problems that forbid publishing ``stages`` under ``out``: per path that exists at
    ``out/<stage>`` and was not written by an earlier publish (see the module docstring), the
    path and why, one line."""
    problems = []
    for stage in stages:
        folder = Path(out) / stage
        if not folder.exists() and not folder.is_symlink():
            continue
        reason = _not_ours(folder, stage)
        if reason:
            problems.append((folder, f"{reason}; stage {stage!r} publishes there (move it away or choose another --out)"))
    return problems


def refused(out: Path) -> str | None:
    """Why ``out`` may not be an ``--out`` at all, or None: a filesystem root, the home folder,
    the project's folder or one of its own folders (:data:`PROJECT_FOLDERS`, and anything in
    them), where the stage folders would land among the system's or the project's files."""
    where = Path(out).expanduser().resolve()
    project = Path(__file__).resolve().parents[1]
    if where == Path(where.anchor):
        what = "the filesystem root"
    elif where == Path.home().resolve():
        what = "the home folder"
    elif where == project:
        what = "the project's folder"
    elif any(where.is_relative_to(project / name) for name in PROJECT_FOLDERS):
        what = "inside the project's own folders"
    else:
        return None
    return f"is {what}: a run writes one folder per stage there (choose a folder of its own)"


def unwritable(out: Path) -> str | None:
    """Why files cannot be published under ``out`` (it cannot be created, or a file cannot be
    made in it: a read-only filesystem, a path through a file), or None; a probe file is made
    and removed."""
    try:
        Path(out).mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".runner-probe.", dir=out)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        return f"cannot write there ({exc.strerror or exc})"
    return None


def _not_ours(folder: Path, stage: str) -> str | None:
    """Why ``folder`` is not an earlier publish of ``stage``, or None if it is."""
    if folder.is_symlink() or not folder.is_dir():
        return "exists and is not a folder published by runner"
    try:
        manifest = json.loads((folder / MANIFEST).read_text())
        listed = {f["path"] for f in manifest["files"]}
        # Manifests written before the "tool" field are recognised by their stage and keys.
        ours = manifest.get("tool", TOOL) == TOOL and manifest.get("stage") == stage and isinstance(manifest["keys"], list)
    except (OSError, ValueError, KeyError, TypeError):
        return f"exists without a {MANIFEST} of runner"
    if not ours:
        return f"its {MANIFEST} was not written by runner for this stage"
    extra = sorted(
        p.relative_to(folder).as_posix()
        for p in folder.rglob("*")
        if (p.is_file() or p.is_symlink()) and p.relative_to(folder).as_posix() not in listed | {MANIFEST}
    )
    if extra:
        return f"holds {len(extra)} file(s) runner did not publish, e.g. {extra[0]!r}"
    return None


def remove_leftovers(out: Path) -> int:
    """Remove the ``.<stage>.<pid>.tmp`` / ``.old`` folders under ``out`` that a publish of
    this tool wrote (:func:`_ours_and_dead`) in a process of this host that is gone; returns
    how many."""
    if not Path(out).is_dir():
        return 0
    removed = 0
    for path in Path(out).iterdir():
        match = _LEFTOVER.match(path.name)
        if match and path.is_dir() and not path.is_symlink() and _ours_and_dead(path, match):
            _remove_marked(path)
            removed += 1
    return removed


def _ours_and_dead(path: Path, match: re.Match[str]) -> bool:
    """Whether leftover folder ``path`` was written by a publish of stage ``match["stage"]`` in
    process ``match["pid"]`` of this host, which is gone: its marker says so, or (an ``.old``
    folder renamed away just before its marker was written) it is a whole published folder."""
    pid, stage = int(match["pid"]), match["stage"]
    try:
        marker = json.loads((path / MARKER).read_text())
    except (OSError, ValueError):
        marker = None
    if isinstance(marker, dict):
        return (
            marker.get("tool") == TOOL and marker.get("stage") == stage and marker.get("pid") == pid and holder_is_stale(marker)
        )
    return (
        path.name.endswith(".old")
        and _not_ours(path, stage) is None
        and holder_is_stale({"pid": pid, "host": socket.gethostname()})
    )


def _mark(folder: Path, stage: str) -> None:
    """Write the :data:`MARKER` of this process into ``folder``."""
    (folder / MARKER).write_text(json.dumps({"tool": TOOL, "stage": stage, "pid": os.getpid(), "host": socket.gethostname()}))


def _remove_marked(folder: Path) -> None:
    """Delete ``folder``, its :data:`MARKER` last, so that a folder half deleted by a killed
    process is still known as this tool's."""
    for child in folder.iterdir():
        if child.name == MARKER:
            continue
        if child.is_dir() and not child.is_symlink():
            shutil.rmtree(child, ignore_errors=True)
        else:
            child.unlink(missing_ok=True)
    (folder / MARKER).unlink(missing_ok=True)
    with contextlib.suppress(OSError):
        folder.rmdir()


def is_current(out: Path, item: Published, records: Path) -> bool:
    """True if ``out/<stage>`` was published from the same entries and every file is still
    there as it was published: its stat record (size, mtime, ctime, inode) is the one kept in
    ``records`` when it was written (a file damaged, rewritten or replaced since is published
    again, also when its times were set back: the ctime cannot be)."""
    final = Path(out) / item.stage
    keys = [e.key for e in item.entries]
    try:
        published = json.loads((final / MANIFEST).read_text())
        kept = json.loads(_record_path(records, final).read_text())
        return (
            published.get("keys") == keys
            and kept.get("keys") == keys
            and sorted(kept["stats"]) == sorted(f["path"] for f in published["files"])
            and all(file_stat(final / path) == stat for path, stat in kept["stats"].items())
        )
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return False


def _record_path(records: Path, final: Path) -> Path:
    """Where the stat records of the files published in folder ``final`` are kept: outside
    ``--out``, so that the published folders hold only the outputs and their manifest (the same
    bytes in every run)."""
    return Path(records) / f"{hashlib.sha256(os.fsencode(final.resolve())).hexdigest()}.json"


def _keep_records(records: Path, final: Path, keys: list[str], listed: list[dict[str, Any]]) -> None:
    """Record the stat of each file published in ``final`` (atomically; a failure only means
    the folder is published again next time)."""
    path = _record_path(records, final)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        stats = {f["path"]: file_stat(final / f["path"]) for f in listed}
        tmp.write_text(json.dumps({"folder": str(final.resolve()), "keys": keys, "stats": stats}))
        os.replace(tmp, path)
    except OSError:
        tmp.unlink(missing_ok=True)


def publish(out: Path, item: Published, *, records: Path, on_damaged: Callable[[Damaged], None]) -> None:
    """Publish ``item`` to ``out/<stage>/`` (one port) or ``out/<stage>/<port>/`` (several),
    unless it is there already (:func:`is_current`, with the stat records kept in ``records``).

    A cache file whose bytes differ from its recorded sha256 is reported to ``on_damaged``, its
    entry recomputed with ``item.redo`` and the folder built again. On any failure (a full
    disk: the :class:`OSError` names the file being written under ``out``) the temporary
    folder is removed.

    Raises
    ------
    StageError
        Two chunks wrote the same file, ``out/<stage>`` is not an earlier publish (created
        since the run started), or an entry is still damaged after it was recomputed.
    """
    out = Path(out)
    if is_current(out, item, records):
        return
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / f".{item.stage}.{os.getpid()}.tmp"
    try:
        listed = _build(out, item, tmp, on_damaged)
    except BaseException:
        if tmp.is_dir():
            _remove_marked(tmp)
        raise
    final = out / item.stage
    old = out / f".{item.stage}.{os.getpid()}.old"
    if old.is_dir():
        _remove_marked(old)
    try:
        os.replace(final, old)
        _mark(old, item.stage)
    except FileNotFoundError:
        pass
    (tmp / MARKER).unlink()
    try:
        os.replace(tmp, final)
        _keep_records(records, final, [e.key for e in item.entries], listed)
    except OSError:  # another run published the same stage meanwhile
        shutil.rmtree(tmp, ignore_errors=True)
    if old.is_dir():
        _remove_marked(old)


def _build(out: Path, item: Published, tmp: Path, on_damaged: Callable[[Damaged], None]) -> list[dict[str, Any]]:
    """Fill the temporary folder ``tmp`` of ``item``: its marker, the verified copies, the
    manifest last; checks that ``out/<stage>`` may still be replaced. Returns the manifest's
    file list."""
    redone: set[int] = set()
    while True:
        if tmp.is_dir():
            _remove_marked(tmp)
        tmp.mkdir()
        _mark(tmp, item.stage)
        try:
            listed = _copy(item, tmp)
            break
        except _DamagedEntry as exc:
            if exc.index in redone:
                raise StageError(f"cache entry still damaged after it was recomputed: {exc.damaged}") from None
            on_damaged(exc.damaged)
            item.entries[exc.index] = item.redo(exc.index)
            redone.add(exc.index)
    manifest = {"tool": TOOL, "stage": item.stage, "uses": item.uses, "keys": [e.key for e in item.entries], "files": listed}
    (tmp / MANIFEST).write_text(json.dumps(manifest, indent=1))
    problems = conflicts(out, [item.stage])
    if problems:
        raise StageError("{}: {}".format(*problems[0]))
    return listed


class _DamagedEntry(Exception):
    def __init__(self, index: int, damaged: Damaged):
        self.index, self.damaged = index, damaged


def _copy(item: Published, tmp: Path) -> list[dict[str, Any]]:
    """Put every file of ``item`` into ``tmp`` as copies hashed while copied
    (:func:`runner.outputs.copy_verified`); the manifest's file list."""
    listed = []
    for port in item.ports:
        target = tmp if len(item.ports) == 1 else tmp / port
        for index, entry in enumerate(item.entries):
            source = output_path(entry, port)
            for rel, size, sha256 in entry.record["outputs"][port]["files"]:
                dest = target / rel
                if dest.exists():
                    raise StageError(f"{port}: two chunks wrote the same file {rel!r}")
                dest.parent.mkdir(parents=True, exist_ok=True)
                try:
                    copy_verified(source / rel, dest, sha256)
                except Damaged as exc:
                    raise _DamagedEntry(index, exc) from None
                listed.append({"path": dest.relative_to(tmp).as_posix(), "size": size, "sha256": sha256})
    return listed
