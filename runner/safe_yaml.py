"""One YAML reader for every file a user hands the tool (pipelines, batch manifests, layouts,
pack manifests).

PyYAML's safe loader still expands aliases: a few lines of nested ``&a [*b, *b, ...]`` (an
"alias bomb") grow to billions of nodes and run the process out of memory. These files never
need aliases, so :class:`StrictLoader` refuses them where they appear, and refuses any tag the
safe constructor does not build (``!!python/object`` and friends) with its position, instead of
failing later while the value is built. It also refuses, with the position of the offending
node: collections nested deeper than :data:`MAX_DEPTH` (PyYAML composes them recursively, and
``[[[[...`` 100,000 deep ends in a ``RecursionError``), and a key given twice in one mapping
(PyYAML keeps the last value silently). :func:`read_text` refuses a file that is not UTF-8 with
the line and column of the first bad byte.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from runner.files import read_limited

MAX_DEPTH = 64  # collections inside collections; the tool's files nest fewer than 10 deep
MAX_BYTES = 16 << 20  # a YAML file's size; the tool's own are under 100 kB


class StrictLoader(yaml.SafeLoader):
    """:class:`yaml.SafeLoader` without aliases, unknown tags, duplicate keys or collections
    nested deeper than :data:`MAX_DEPTH`; each raises :class:`yaml.MarkedYAMLError` at the
    offending node (``problem_mark``: line, column)."""

    def __init__(self, stream: Any) -> None:
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()  # type: ignore[no-untyped-call]
            raise yaml.composer.ComposerError(
                None, None, f"alias *{event.anchor} is not allowed (aliases are refused)", event.start_mark
            )
        if self.check_event(yaml.SequenceStartEvent, yaml.MappingStartEvent) and self._depth >= MAX_DEPTH:
            raise yaml.composer.ComposerError(None, None, f"nested deeper than {MAX_DEPTH} levels", self.peek_event().start_mark)  # type: ignore[no-untyped-call]
        self._depth += 1
        try:
            node: yaml.Node = super().compose_node(parent, index)  # type: ignore[assignment]  # None only at the stream end
        finally:
            self._depth -= 1
        if node.tag not in self.yaml_constructors:
            raise yaml.constructor.ConstructorError(None, None, f"tag {node.tag!r} is not allowed", node.start_mark)
        return node

    # PyYAML passes the node's anchor (types-PyYAML declares a dict)
    def compose_mapping_node(self, anchor: str | None) -> yaml.MappingNode:  # type: ignore[override]
        node = super().compose_mapping_node(anchor)  # type: ignore[arg-type]
        first: dict[tuple[str, str], yaml.Node] = {}
        for key, _ in node.value:
            if not isinstance(key, yaml.ScalarNode):
                continue
            seen = first.setdefault((key.tag, key.value), key)
            if seen is not key:
                mark = seen.start_mark
                raise yaml.composer.ComposerError(
                    None,
                    None,
                    f"duplicate key {key.value!r} (first at line {mark.line + 1}, column {mark.column + 1})",
                    key.start_mark,
                )
        return node


def read_text(path: str | Path) -> str:
    """The text of the YAML file ``path``, which must be a regular file of at most
    :data:`MAX_BYTES` bytes of UTF-8 (:func:`runner.files.read_limited`).

    Raises
    ------
    OSError
        The file cannot be read, is not a regular file (a FIFO, ``/dev/zero``) or is larger.
    yaml.MarkedYAMLError
        A byte sequence is not UTF-8; ``problem_mark`` is its line and column (bytes).
    """
    data = read_limited(path, MAX_BYTES)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line_start = data.rfind(b"\n", 0, exc.start) + 1
        mark = yaml.Mark(str(path), exc.start, data.count(b"\n", 0, exc.start), exc.start - line_start, None, None)  # type: ignore[arg-type]  # no buffer
        raise yaml.MarkedYAMLError(
            problem=f"not UTF-8 text (byte 0x{data[exc.start]:02x}: {exc.reason})", problem_mark=mark
        ) from None


def compose(text: str, name: str = "<unicode string>") -> yaml.Node | None:
    """The node tree of one YAML document (positions kept), read with :class:`StrictLoader`;
    ``name`` (the file it came from) is the ``name`` of every node's marks."""
    loader = StrictLoader(text)
    loader.name = name
    try:
        return loader.get_single_node()
    finally:
        loader.dispose()


def load(text: str) -> Any:
    """The value of one YAML document, read with :class:`StrictLoader`."""
    return yaml.load(text, Loader=StrictLoader)  # noqa: S506 - StrictLoader derives from SafeLoader


def error_position(exc: yaml.YAMLError, source: str | Path) -> str:
    """``source:line:column`` of a YAML error (1-based), or ``source`` when it has no position."""
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    return f"{source}:{mark.line + 1}:{mark.column + 1}" if mark is not None else str(source)


def error_message(exc: yaml.YAMLError) -> str:
    """The problem a YAML error describes, on one line."""
    if isinstance(exc, yaml.MarkedYAMLError):
        return str(exc.problem or exc.context)
    return str(exc).splitlines()[0]
