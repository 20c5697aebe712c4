"""The one renderer of every report: a list of sections as Markdown and as a standalone HTML page,
plots inline, so both say the same thing.

A section is ``(title, kind, content)``: kind ``text`` (a string), ``list`` (a dict shown as
"key: value" items), ``table`` (a polars DataFrame; floats to 3 significant digits, written for
people: ``1.2e-84``, never ``1.1999999999999999e-84``; a missing or undefined value (null, NaN)
shows as 'n/a'), ``captioned`` (a ``(text, DataFrame)`` pair: one heading, the text above its
table) or ``image`` (PNG bytes).
"""

from __future__ import annotations

import base64
import html
import math
from collections.abc import Sequence
from typing import Any

import polars as pl

Section = tuple[str, str, Any]

STYLE = ("<style>body{font-family:sans-serif;max-width:1400px;margin:2em auto}table{border-collapse:collapse;"
         "font-size:13px}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right;vertical-align:top}"
         "img{max-width:100%}</style>")


def markdown_image(png: bytes, alt: str = "plot") -> str:
    """A Markdown image with the PNG inline (renders in the Dagster UI and in reports)."""
    return f"![{alt}](data:image/png;base64,{base64.b64encode(png).decode()})"


NOT_AVAILABLE = "n/a"  # a table cell whose value is missing or not defined (null, NaN)
TABLE_DIGITS = 3  # significant digits of the floats in report tables


def _cell(v, digits: int | None = None) -> str:
    """A table cell for people: floats to ``digits`` significant digits, missing or undefined as n/a."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return NOT_AVAILABLE
    return f"{v:.{digits}g}" if isinstance(v, float) and digits is not None else str(v)


def markdown_table(df: pl.DataFrame, digits: int = 4) -> str:
    """A polars table as a Markdown table (floats to ``digits`` significant digits, missing as n/a)."""
    lines = ["| " + " | ".join(df.columns) + " |", "|" + "---|" * len(df.columns)]
    lines += ["| " + " | ".join(_cell(v, digits) for v in row) + " |" for row in df.iter_rows()]
    return "\n".join(lines)


def _table_of(kind: str, content) -> tuple[str, pl.DataFrame]:
    """(caption, table) of a ``table`` or ``captioned`` section."""
    return content if kind == "captioned" else ("", content)


def to_markdown(title: str, secs: Sequence[Section], images: dict[str, str] | None = None) -> str:
    """The sections as Markdown; ``images``: section title -> the PNG's path relative to the .md
    (the PNG beside it), else the PNG inline as base64."""
    lines = [f"# {title}", ""]
    for name, kind, content in secs:
        lines += [f"## {name}", ""]
        if kind == "text":
            lines.append(str(content))
        elif kind == "list":
            lines += [f"- **{k}**: {v}" for k, v in content.items()]
        elif kind in ("table", "captioned"):
            caption, table = _table_of(kind, content)
            if caption:
                lines += [caption, ""]
            lines.append(markdown_table(table, TABLE_DIGITS) if table.height else "(none)")
        elif images and name in images:
            lines.append(f"![{name}]({images[name]})")
        else:
            lines.append(markdown_image(content, name))
        lines.append("")
    return "\n".join(lines)


def to_html(title: str, secs: Sequence[Section]) -> str:
    """The sections as one self-contained HTML page (PNGs inline)."""
    esc = html.escape
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{esc(title)}</title>", STYLE,
             f"</head><body><h1>{esc(title)}</h1>"]
    for name, kind, content in secs:
        parts.append(f"<h2>{esc(name)}</h2>")
        if kind == "text":
            parts.append(f"<p>{esc(str(content))}</p>")
        elif kind == "list":
            parts.append("<ul>" + "".join(f"<li><b>{esc(k)}</b>: {esc(str(v))}</li>" for k, v in content.items())
                         + "</ul>")
        elif kind in ("table", "captioned"):
            caption, t = _table_of(kind, content)
            if caption:
                parts.append(f"<p>{esc(caption)}</p>")
            head = "".join(f"<th>{esc(c)}</th>" for c in t.columns)
            body = "".join("<tr>" + "".join(f"<td>{esc(_cell(v, TABLE_DIGITS))}</td>" for v in row) + "</tr>"
                           for row in t.iter_rows())
            parts.append(f"<table><tr>{head}</tr>{body}</table>")
        else:
            parts.append(f"<img alt='{esc(name)}' src='data:image/png;base64,{base64.b64encode(content).decode()}'>")
    parts.append("</body></html>")
    return "\n".join(parts)
