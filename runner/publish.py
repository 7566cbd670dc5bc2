"""Publishing ``files`` outputs to ``--out/<stage>/``: whole or absent, verified, never over a
user's files.

A stage's folder is built as ``--out/.<stage>.<pid>.tmp``, each file hashed and compared with
the sha256 its cache entry recorded (unless its size, mtime and inode are those recorded in the
entry's ``verified.json`` when it was last found intact), then hard-linked from the entry (copied where the two lie
on different filesystems), ``manifest.json`` (the file list
with sizes and sha256, and the entries' keys) written last; then the old folder is moved to
``.<stage>.<pid>.old``, the new one into place, and the old one deleted.

What may be replaced: only a folder whose ``manifest.json`` names this tool and this stage and
lists every file in it, i.e. what an earlier publish wrote. Anything else at ``--out/<stage>``
(a user's folder or file that happens to have a stage's name, a file added inside a published
folder) is reported by :func:`conflicts` before anything runs. Leftover ``.<stage>.<pid>.tmp``
and ``.old`` folders of processes that are gone (a kill between the two renames) are removed by
:func:`remove_leftovers`, which every run and ``runner cache gc --out`` call.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from runner.cache import Entry, holder_is_stale
from runner.outputs import Damaged, link_verified, output_path, save_verified_stats, verified_stats
from runner.stage import StageError

MANIFEST = "manifest.json"
TOOL = "expression-mapping runner"
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


def conflicts(out: Path, stages: Iterable[str]) -> list[str]:
    """Problems that forbid publishing ``stages`` under ``out``, one line each: a path that
    exists at ``out/<stage>`` and was not written by an earlier publish (see the module
    docstring)."""
    problems = []
    for stage in stages:
        folder = Path(out) / stage
        if not folder.exists() and not folder.is_symlink():
            continue
        reason = _not_ours(folder, stage)
        if reason:
            problems.append(f"{folder}: {reason}; it would be replaced by the outputs of stage {stage!r} "
                            "(move it away or choose another --out)")
    return problems


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
    extra = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*")
                   if (p.is_file() or p.is_symlink()) and p.relative_to(folder).as_posix() not in listed | {MANIFEST})
    if extra:
        return f"holds {len(extra)} file(s) runner did not publish, e.g. {extra[0]!r}"
    return None


def remove_leftovers(out: Path) -> int:
    """Remove ``.<stage>.<pid>.tmp`` / ``.old`` folders under ``out`` left by processes of this
    host that are gone; returns how many."""
    if not Path(out).is_dir():
        return 0
    removed = 0
    for path in Path(out).iterdir():
        match = _LEFTOVER.match(path.name)
        if match and path.is_dir() and holder_is_stale({"pid": int(match["pid"]), "host": socket.gethostname()}):
            shutil.rmtree(path, ignore_errors=True)
            removed += 1
    return removed


def is_current(out: Path, item: Published) -> bool:
    """True if ``out/<stage>`` was published from the same entries and every file is still
    there with its size (a damaged or deleted output is published again)."""
    final = Path(out) / item.stage
    try:
        published = json.loads((final / MANIFEST).read_text())
        return published.get("keys") == [e.key for e in item.entries] and all(
            (final / f["path"]).is_file() and (final / f["path"]).stat().st_size == f["size"]
            for f in published["files"])
    except (OSError, ValueError, KeyError, TypeError):
        return False


def publish(out: Path, item: Published, *, on_damaged: Callable[[Damaged], None]) -> None:
    """Publish ``item`` to ``out/<stage>/`` (one port) or ``out/<stage>/<port>/`` (several).

    A cache file whose bytes differ from its recorded sha256 is reported to ``on_damaged``, its
    entry recomputed with ``item.redo`` and the folder built again.

    Raises
    ------
    StageError
        Two chunks wrote the same file, ``out/<stage>`` is not an earlier publish (created
        since the run started), or an entry is still damaged after it was recomputed.
    """
    out = Path(out)
    if is_current(out, item):
        return
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / f".{item.stage}.{os.getpid()}.tmp"
    redone: set[int] = set()
    while True:
        shutil.rmtree(tmp, ignore_errors=True)
        try:
            listed = _copy(item, tmp)
            break
        except _DamagedEntry as exc:
            if exc.index in redone:
                raise StageError(f"cache entry still damaged after it was recomputed: {exc.damaged}") from None
            on_damaged(exc.damaged)
            item.entries[exc.index] = item.redo(exc.index)
            redone.add(exc.index)
    manifest = {"tool": TOOL, "stage": item.stage, "uses": item.uses, "keys": [e.key for e in item.entries],
                "files": listed}
    (tmp / MANIFEST).write_text(json.dumps(manifest, indent=1))
    final = out / item.stage
    problems = conflicts(out, [item.stage])
    if problems:
        shutil.rmtree(tmp, ignore_errors=True)
        raise StageError(problems[0])
    old = out / f".{item.stage}.{os.getpid()}.old"
    shutil.rmtree(old, ignore_errors=True)
    try:
        os.replace(final, old)
    except FileNotFoundError:
        pass
    try:
        os.replace(tmp, final)
    except OSError:  # another run published the same stage meanwhile
        shutil.rmtree(tmp, ignore_errors=True)
    shutil.rmtree(old, ignore_errors=True)


class _DamagedEntry(Exception):
    def __init__(self, index: int, damaged: Damaged):
        self.index, self.damaged = index, damaged


def _copy(item: Published, tmp: Path) -> list[dict]:
    """Put every file of ``item`` into ``tmp``, verified, hard-linked to its cache entry where
    the filesystem allows (:func:`runner.outputs.link_verified`); the manifest's file list."""
    listed = []
    stats = [verified_stats(entry) for entry in item.entries]
    checked = [dict(known) for known in stats]
    for port in item.ports:
        target = tmp if len(item.ports) == 1 else tmp / port
        for index, entry in enumerate(item.entries):
            source = output_path(entry, port)
            for rel, size, sha256 in entry.record["outputs"][port]["files"]:
                dest = target / rel
                if dest.exists():
                    raise StageError(f"{port}: two chunks wrote the same file {rel!r}")
                dest.parent.mkdir(parents=True, exist_ok=True)
                name = (source / rel).relative_to(entry.path).as_posix()
                try:
                    checked[index][name] = link_verified(source / rel, dest, sha256, stat=stats[index].get(name))
                except Damaged as exc:
                    raise _DamagedEntry(index, exc) from None
                listed.append({"path": dest.relative_to(tmp).as_posix(), "size": size, "sha256": sha256})
    for entry, known, now in zip(item.entries, stats, checked):
        if now != known:
            save_verified_stats(entry, now)
    return listed
