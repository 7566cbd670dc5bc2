"""Elementwise functions of half-float frames by table lookup.

A half float has 65536 bit patterns, fewer than the values in one 600x800 RGB frame, so an
elementwise function of a ``float16`` array is computed once for every pattern and then looked
up by the array's bits: the same values as calling the function on the array (it is the
function's own output, bit for bit), for one indexing pass instead of its arithmetic. The
synthesized frames are half floats; ``write.exr`` decodes them to linear light this way (their
8-bit quantization for H.264 and the preview is one OpenCV pass, :func:`stages.color.to_uint8`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np

Elementwise = Callable[[np.ndarray], np.ndarray]


@functools.cache
def half_table(fn: Elementwise) -> np.ndarray:
    """``fn`` of every float16 bit pattern: ``(65536,)`` array indexed by ``x.view(uint16)``."""
    with np.errstate(all="ignore"):  # the patterns include inf and NaN
        table = np.asarray(fn(np.arange(1 << 16, dtype=np.uint16).view(np.float16)))
    if table.shape != (1 << 16,):
        raise ValueError(f"half_table: {fn.__name__} must be elementwise, got shape {table.shape} for (65536,)")
    table.flags.writeable = False
    return table


def apply_elementwise(fn: Elementwise, array: np.ndarray) -> np.ndarray:
    """``fn(array)`` for an elementwise ``fn``: by lookup in :func:`half_table` when ``array`` is
    ``float16`` (same values, any shape), else by calling ``fn``.

    ``fn`` must be a module-level function (the table is kept per function object) whose value
    at an element depends on that element alone.
    """
    if array.dtype != np.float16:
        return fn(array)
    return half_table(fn)[array.view(np.uint16)]  # any strides; the result is C-contiguous
