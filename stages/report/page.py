"""The report page: one self-contained HTML file (images as data URIs, no script, no network).

The numbers behind the plots are embedded as JSON in ``<script type="application/json"
id="report-data">`` (never executed), so anyone can check a curve against the run's data.
"""

from __future__ import annotations

import base64
import html
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

STYLE = """
body { font: 14px/1.45 system-ui, sans-serif; margin: 1.5em auto; max-width: 1100px; padding: 0 1em; color: #222; }
h1 { font-size: 1.5em; margin-bottom: 0.2em; } h2 { font-size: 1.15em; margin-top: 1.6em; border-bottom: 1px solid #ddd; }
.meta { color: #555; } .warn li { color: #8a4b00; } .none { color: #777; font-style: italic; }
.sheet { display: grid; grid-template-columns: repeat(auto-fill, minmax(250px, 1fr)); gap: 10px; }
figure { margin: 0; } figure img { width: 100%; height: auto; display: block; border: 1px solid #ccc; }
figcaption { font-size: 12px; color: #444; } img.plot { max-width: 100%; height: auto; }
table { border-collapse: collapse; } td, th { border: 1px solid #ddd; padding: 2px 8px; text-align: right; }
"""


@dataclass(frozen=True)
class Section:
    """One titled part of the page: an HTML body (already escaped) and an optional note."""

    title: str
    body: str


def data_uri(data: bytes, mime: str) -> str:
    """``data:<mime>;base64,...`` for embedding ``data`` in the page."""
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"


def image(data: bytes, mime: str, alt: str, *, css: str = "plot") -> str:
    """An ``<img>`` element with the image embedded."""
    return f'<img class="{css}" alt="{html.escape(alt)}" src="{data_uri(data, mime)}">'


def not_available(reason: str) -> str:
    """A paragraph saying what is missing and why."""
    return f'<p class="none">Not available: {html.escape(reason)}</p>'


def listing(items: Sequence[str], *, css: str = "") -> str:
    """An HTML list of plain-text items."""
    rows = "".join(f"<li>{html.escape(item)}</li>" for item in items)
    return f'<ul class="{css}">{rows}</ul>'


def table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """An HTML table of plain-text cells."""
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def to_json(value: object) -> object:
    """Arrays and numpy scalars to plain JSON values; NaN and infinities become null."""
    if isinstance(value, Mapping):
        return {str(k): to_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_json(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_json(value.tolist())
    if isinstance(value, np.generic):
        return to_json(value.item())
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def page(*, title: str, meta: str, sections: Sequence[Section], data: Mapping[str, object]) -> str:
    """The whole HTML document.

    Parameters
    ----------
    title : the heading; meta : one line under it (plain text).
    sections : in order.
    data : the series behind the plots, embedded as JSON (see :func:`to_json`).
    """
    payload = json.dumps(to_json(data), sort_keys=True, allow_nan=False, separators=(",", ":"))
    payload = payload.replace("</", "<\\/")  # cannot close the script element
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{html.escape(title)}</title><style>{STYLE}</style></head><body>",
        f'<h1>{html.escape(title)}</h1><p class="meta">{html.escape(meta)}</p>',
    ]
    parts += [f"<section><h2>{html.escape(s.title)}</h2>{s.body}</section>" for s in sections]
    parts.append(f'<script type="application/json" id="report-data">{payload}</script>')
    parts.append("</body></html>\n")
    return "\n".join(parts)
