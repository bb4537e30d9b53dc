"""A report as a list of blocks, written twice: as Markdown (`to_markdown`) and as HTML
(`to_html`), so that report.md and report.html cannot say different things; `write_documents`
writes both. Headings, paragraphs, facts (a bulleted label: value list), tables of text cells
and images linked relative to the document. The one home of the reports' HTML: a training
run's (alignrl.runs.report) and a league's (alignrl.league.report).
"""

from __future__ import annotations

import html
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote

__all__ = [
    "Block",
    "Facts",
    "Heading",
    "Image",
    "Paragraph",
    "Table",
    "to_html",
    "to_markdown",
    "write_documents",
]


@dataclass(frozen=True)
class Heading:
    level: int
    text: str


@dataclass(frozen=True)
class Paragraph:
    text: str


@dataclass(frozen=True)
class Facts:
    items: list[tuple[str, str]]  # (label, what it is), one bullet each


@dataclass(frozen=True)
class Table:
    header: list[str]
    rows: list[list[str]]


@dataclass(frozen=True)
class Image:
    title: str
    path: str  # relative to the document


Block = Heading | Paragraph | Facts | Table | Image


def to_markdown(blocks: Sequence[Block]) -> str:
    def cell(text: str) -> str:
        return text.replace("|", "\\|")

    lines: list[str] = []
    for block in blocks:
        match block:
            case Heading(level, text):
                lines.append(f"{'#' * level} {text}")
            case Paragraph(text):
                lines.append(text)
            case Facts(items):
                lines += [f"- **{label}:** {value}" for label, value in items]
            case Table(header, rows):
                lines += [
                    "| " + " | ".join(map(cell, header)) + " |",
                    "|" + " --- |" * len(header),
                    *("| " + " | ".join(map(cell, row)) + " |" for row in rows),
                ]
            case Image(title, path):
                lines.append(f"![{title}]({quote(path)})")
        lines.append("")
    return "\n".join(lines)


HTML_STYLE = (
    "body{font-family:sans-serif;max-width:72rem;margin:2rem auto;padding:0 1rem}"
    "table{border-collapse:collapse}th,td{border:1px solid #bbb;padding:.2rem .5rem}"
    "th{background:#eee}img{max-width:100%}"
)


def to_html(title: str, blocks: Sequence[Block]) -> str:
    escape = html.escape
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en">',
        f'<head><meta charset="utf-8"><title>{escape(title)}</title>'
        f"<style>{HTML_STYLE}</style></head>",
        "<body>",
    ]
    for block in blocks:
        match block:
            case Heading(level, text):
                parts.append(f"<h{level}>{escape(text)}</h{level}>")
            case Paragraph(text):
                parts.append(f"<p>{escape(text)}</p>")
            case Facts(items):
                parts.append(
                    "<ul>"
                    + "".join(f"<li><b>{escape(k)}:</b> {escape(v)}</li>" for k, v in items)
                    + "</ul>"
                )
            case Table(header, rows):
                head = "".join(f"<th>{escape(text)}</th>" for text in header)
                body = "".join(
                    "<tr>" + "".join(f"<td>{escape(text)}</td>" for text in row) + "</tr>"
                    for row in rows
                )
                parts.append(f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>")
            case Image(title, path):
                parts.append(f'<p><img src="{escape(quote(path))}" alt="{escape(title)}"></p>')
    parts += ["</body>", "</html>", ""]
    return "\n".join(parts)


def write_documents(stem: Path, title: str, blocks: Sequence[Block]) -> tuple[Path, Path]:
    """Write `stem`.md and `stem`.html (each replaced atomically, the Markdown last: a reader
    that finds it finds both); return their paths."""
    from alignrl.checkpoints import atomic_write_text

    markdown, page = stem.with_suffix(".md"), stem.with_suffix(".html")
    atomic_write_text(page, to_html(title, blocks))
    atomic_write_text(markdown, to_markdown(blocks))
    return markdown, page
