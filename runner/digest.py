"""Content digests (sha256) of arrays, bundles, files and folders, and cache keys.

A cache key is the sha256 of a canonical JSON document (sorted keys, no spaces, UTF-8) holding
everything that determines a result: stage name and version, parameters, input digests, chunk
range, the device and the versions of the libraries that change results.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import json
import os
import platform
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from runner.files import open_regular

# Distributions whose version can change a stage's numbers. The OpenCV wheel goes by several
# distribution names; whichever are installed are recorded.
RESULT_LIBRARIES = (
    "numpy",
    "scipy",
    "torch",
    "kornia",
    "opencv-python",
    "opencv-python-headless",
    "opencv-contrib-python",
    "opencv-contrib-python-headless",
    "av",
    "OpenImageIO",
)
_BLOCK = 1 << 20


def canonical_json(value: Any) -> str:
    """JSON with sorted keys and no whitespace: equal values give equal text."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)


def cache_key(material: Any) -> str:
    """sha256 hex digest of :func:`canonical_json` of ``material``."""
    return hashlib.sha256(canonical_json(material).encode("utf-8")).hexdigest()


@functools.cache
def library_versions() -> dict[str, str]:
    """Installed versions of :data:`RESULT_LIBRARIES` (read from package metadata, without
    importing them) and of Python; a library that is not installed is recorded as such."""
    versions = {"python": platform.python_version()}
    for dist in RESULT_LIBRARIES:
        try:
            versions[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            if not dist.startswith("opencv"):
                versions[dist] = "not installed"
    return versions


def array_digest(array: np.ndarray) -> str:
    """sha256 over dtype, shape and the C-order bytes of ``array`` (object arrays refused)."""
    if array.dtype.hasobject:
        raise TypeError("object arrays cannot be hashed or stored without pickle")
    h = hashlib.sha256(canonical_json({"dtype": array.dtype.str, "shape": list(array.shape)}).encode())
    h.update(memoryview(np.ascontiguousarray(array)).cast("B"))  # type: ignore[arg-type]  # numpy arrays are buffers
    return h.hexdigest()


def bundle_digest(bundle: Mapping[str, np.ndarray]) -> str:
    """sha256 over the sorted keys of a bundle and the :func:`array_digest` of each value."""
    return cache_key({name: array_digest(np.asarray(bundle[name])) for name in sorted(bundle)})


def file_digest(path: Path) -> str:
    """sha256 of a regular file's bytes (:func:`runner.files.open_regular`: a FIFO or a device
    is an :class:`OSError`, never read)."""
    h = hashlib.sha256()
    with open_regular(path) as f:
        while block := f.read(_BLOCK):
            h.update(block)
    return h.hexdigest()


def tree_files(folder: Path) -> list[Path]:
    """Every file under ``folder`` (sub-folders included), sorted: what :func:`tree_digest`
    covers."""
    return sorted(p for p in Path(folder).rglob("*") if p.is_file())


def tree_digest(folder: Path) -> str:
    """sha256 over the relative paths (POSIX, sorted) and byte digests of every file under
    ``folder``; empty folders and file times do not count. A path that is not valid UTF-8 (a
    file name in another encoding) counts by its bytes (:func:`path_text`)."""
    return cache_key([[path_text(p.relative_to(folder)), file_digest(p)] for p in tree_files(folder)])


def path_text(path: Path) -> str | list[str]:
    """``path`` as POSIX text for a canonical JSON document; a path whose bytes are not UTF-8
    (decoded by Python with surrogate escapes) as ``["bytes", HEX]`` of those bytes, so that
    distinct names never collide."""
    text = path.as_posix()
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return ["bytes", os.fsencode(text).hex()]
    return text


def combine(parts: list[str]) -> str:
    """One digest for an ordered list of digests (a frame stream from its chunks)."""
    return cache_key(parts)


def input_digest(kind: str, path: Path) -> str:
    """Digest of a pipeline input of type ``video``, ``file`` (the file's bytes) or ``dir``
    (:func:`tree_digest`), with the name's suffix: a stage may parse a file by its suffix
    (``init.csv`` and ``init.json`` with the same bytes are different inputs)."""
    path = Path(path)
    content = tree_digest(path) if kind == "dir" else file_digest(path)
    return cache_key({"kind": kind, "suffix": path.suffix, "content": content})
