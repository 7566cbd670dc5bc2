"""Declared bundle types: the fields, dtypes, shapes and units of the data stages pass each other.

A bundle is a ``dict[str, numpy.ndarray]`` (:mod:`runner.stage`). Its type is declared in code by
the package that produces it, as a :class:`BundleType` naming its fields; stages use the object as
the port type in ``inputs``/``outputs``. The runner connects two ports when the output's type name
is one the input accepts (checked when the graph is loaded, :mod:`runner.config`), and checks each
bundle a stage returns against its declared type before storing it (:mod:`runner.outputs`).

A port type may also be a plain string: one of the runner's types (``video``, ``file``, ``dir``,
``frames``, ``files``), or the name of an undeclared bundle, which connects by name and whose
fields are not checked. An input that takes one of several bundle types declares them as a
tuple.

Shapes
------
A shape is a tuple of dimensions: an ``int`` is a fixed extent, a string a symbolic one that must
be the same in every field of the bundle where it appears (``"T"``, the frame count; ``"N"``, the
points), and ``"*"`` any extent. Fields a bundle carries beyond the declared ones are not
checked.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Union

#: Numpy dtype kinds by the word the documentation shows for them.
KIND_WORDS = {"b": "bool", "i": "int", "u": "uint", "f": "float", "U": "str"}

Dim = Union[int, str]


@dataclass(frozen=True)
class Field:
    """One field of a bundle type.

    ``kinds``: the numpy dtype kinds allowed (``"f"`` float, ``"b"`` bool, ``"i"`` signed and
    ``"u"`` unsigned integer, ``"U"`` str; ``"iu"`` either integer). ``shape``: dimensions as in
    the module's docstring, ``()`` a scalar. ``unit``: e.g. ``"px"``, ``"mm"``, ``"deg"``, empty
    when none.
    """

    name: str
    kinds: str
    shape: tuple[Dim, ...]
    unit: str = ""
    doc: str = ""
    optional: bool = False

    def dtype_text(self) -> str:
        """The allowed dtypes in words: ``float``, ``int/uint``."""
        return "/".join(KIND_WORDS.get(k, k) for k in self.kinds)

    def shape_text(self) -> str:
        """The shape as written in the docs: ``(T, N, 2)``, ``()``."""
        return "(" + ", ".join(map(str, self.shape)) + ("," if len(self.shape) == 1 else "") + ")"


@dataclass(frozen=True)
class BundleType:
    """A bundle's declared type: its name (the port type name), what it holds and its fields."""

    name: str
    doc: str
    fields: tuple[Field, ...]

    def __str__(self) -> str:
        return self.name

    def problems(self, bundle: Mapping[str, Any]) -> list[str]:
        """What in ``bundle`` does not match the declaration, one sentence per problem (empty:
        it matches): a missing required field, a dtype of another kind, another rank, a fixed
        dimension of another extent, or a symbolic dimension of two extents."""
        import numpy as np  # here: runner.stage imports this module, and `runner --help` starts without numpy

        found: list[str] = []
        extents: dict[str, tuple[int, str]] = {}  # symbolic dim -> (extent, first field that set it)
        for f in self.fields:
            if f.name not in bundle:
                if not f.optional:
                    found.append(f"field {f.name!r} is missing")
                continue
            array = np.asarray(bundle[f.name])
            if array.dtype.kind not in f.kinds:
                found.append(f"field {f.name!r} is {array.dtype}, expected {f.dtype_text()}")
            if array.ndim != len(f.shape):
                found.append(f"field {f.name!r} has shape {array.shape}, expected {f.shape_text()}")
                continue
            if any(isinstance(dim, int) and extent != dim for dim, extent in zip(f.shape, array.shape)):
                found.append(f"field {f.name!r} has shape {array.shape}, expected {f.shape_text()}")
                continue
            for axis, (dim, extent) in enumerate(zip(f.shape, array.shape)):
                if isinstance(dim, str) and dim != "*":
                    seen = extents.setdefault(dim, (extent, f.name))
                    if seen[0] != extent:
                        found.append(
                            f"field {f.name!r} has {dim} = {extent} (axis {axis}), field {seen[1]!r} has {dim} = {seen[0]}"
                        )
        return found


#: What a stage declares for a port: a runner type or undeclared bundle name, a bundle type, or
#: (inputs only) a tuple of the bundle types it accepts.
PortType = Union[str, BundleType, tuple[BundleType, ...]]


def type_names(port_type: PortType) -> tuple[str, ...]:
    """The type names a port type stands for (several for an input accepting a tuple)."""
    if isinstance(port_type, tuple):
        return tuple(t.name for t in port_type)
    return (port_type.name if isinstance(port_type, BundleType) else port_type,)


def describe(port_type: PortType) -> str:
    """The port type as ``runner stages`` and the messages show it: ``points``, ``a | b``."""
    return " | ".join(type_names(port_type))


def accepts(expected: PortType, got: PortType) -> bool:
    """Whether an input declared ``expected`` takes an output declared ``got`` (by type name)."""
    return describe(got) in type_names(expected)
