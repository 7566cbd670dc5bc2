"""One reader for the ``.npz`` files a user hands the tool (a pack's ``captured.npz`` and points
files, a points file, a run's ``data.npz`` given to the editor).

``numpy.load`` builds an array from whatever shape its header states: a 3 MB file of
compressed zeros declaring a million geometries takes 8 GB and minutes before any check can
look at it, and an empty or truncated file raises ``EOFError`` or ``BadZipFile``, which no
caller expects. :func:`read_npz` reads each array's header first and refuses, before
decompressing anything, an array of more values than the caller allows or one that needs pickle;
every problem is one :class:`NpzError` naming the file (and the array).
"""

from __future__ import annotations

import math
import zipfile
from collections.abc import Collection
from pathlib import Path

import numpy as np


class NpzError(ValueError):
    """An ``.npz`` cannot be read, or holds an array it may not (too large, pickled)."""


def read_npz(path: str | Path, keys: Collection[str], *, max_values: int) -> dict[str, np.ndarray]:
    """The arrays named ``keys`` that the ``.npz`` file ``path`` holds (a missing one is left
    out: the caller names what it needs).

    Parameters
    ----------
    path
        The file.
    keys
        The arrays to read.
    max_values
        The most values (elements) one array may hold; its header is checked before it is read.

    Raises
    ------
    NpzError
        Not a readable ``.npz`` (empty, truncated, not a zip of ``.npy`` files), an array of
        more than ``max_values`` values, or an object array (pickle).
    """
    arrays = {}
    try:
        with zipfile.ZipFile(path) as archive:
            members = {name.removesuffix(".npy"): name for name in archive.namelist() if name.endswith(".npy")}
            for key in keys:
                if key not in members:
                    continue
                with archive.open(members[key]) as member:
                    shape, dtype = _header(member)
                    count = math.prod(shape)
                    if dtype.hasobject:
                        raise NpzError(f"{path}: array {key!r} holds Python objects (pickle is refused)")
                    if count > max_values:
                        raise NpzError(
                            f"{path}: array {key!r} has shape {shape}: {count} values, more than the {max_values} allowed here"
                        )
                with archive.open(members[key]) as member:
                    arrays[key] = np.lib.format.read_array(member, allow_pickle=False)
    except NpzError:
        raise
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, KeyError) as exc:
        raise NpzError(f"{path}: not a readable .npz ({exc or type(exc).__name__})") from None
    return arrays


def _header(member) -> tuple[tuple[int, ...], np.dtype]:
    """``(shape, dtype)`` from the header of an ``.npy`` stream (format 1.0 or 2.0)."""
    version = np.lib.format.read_magic(member)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(member)
    elif version == (2, 0):
        shape, _, dtype = np.lib.format.read_array_header_2_0(member)
    else:
        raise ValueError(f".npy format {version[0]}.{version[1]} is not read")
    return shape, dtype
