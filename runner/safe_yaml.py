"""One YAML reader for every file a user hands the tool (pipelines, layouts, pack manifests).

PyYAML's safe loader still expands aliases: a few lines of nested ``&a [*b, *b, ...]`` (an
"alias bomb") grow to billions of nodes and run the process out of memory. These files never
need aliases, so :class:`StrictLoader` refuses them where they appear, and refuses any tag the
safe constructor does not build (``!!python/object`` and friends) with its position, instead of
failing later while the value is built.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml


class StrictLoader(yaml.SafeLoader):
    """:class:`yaml.SafeLoader` without aliases and without unknown tags; both raise
    :class:`yaml.MarkedYAMLError` at the offending node (``problem_mark``: line, column)."""

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(None, None, f"alias *{event.anchor} is not allowed (aliases are refused)",
                                              event.start_mark)
        node = super().compose_node(parent, index)
        if node.tag not in self.yaml_constructors:
            raise yaml.constructor.ConstructorError(None, None, f"tag {node.tag!r} is not allowed", node.start_mark)
        return node


def compose(text: str) -> yaml.Node | None:
    """The node tree of one YAML document (positions kept), read with :class:`StrictLoader`."""
    return yaml.compose(text, Loader=StrictLoader)


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
