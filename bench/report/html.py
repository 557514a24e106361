"""``report.html``: one self-contained page, the plots embedded as base64 PNG.

No external files, scripts or style sheets: the page can be mailed,
archived or printed as is. A page is a title, a verdict, an identity block
and sections; a section holds blocks in order: paragraphs (``str``),
key/value tables (:class:`KeyValues`), tables with a header row
(:class:`Grid`) and captioned figures (:class:`Figure`). What goes where is
decided by :mod:`servobench.bench.report.commission_record`.
"""

from __future__ import annotations

import base64
import html
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

REPORT_FILE = "report.html"

#: Verdict words and their CSS class.
PASS, REMARK, FAIL = "pass", "remark", "fail"

_STYLE = """
body{font-family:sans-serif;max-width:62em;margin:2em auto;padding:0 1em;color:#222;line-height:1.35}
h1{font-size:1.5em;margin-bottom:.2em} h2{font-size:1.25em;border-bottom:2px solid #bbb;margin-top:2em}
h3{font-size:1.05em;margin-top:1.6em;border-bottom:1px solid #ddd}
table{border-collapse:collapse;margin:.5em 0} td,th{border:1px solid #ccc;padding:.25em .6em;text-align:left;vertical-align:top}
thead th{background:#f0f0f0} td.num{text-align:right;font-variant-numeric:tabular-nums;white-space:nowrap}
caption{text-align:left;font-weight:bold;padding:.2em 0}
img{max-width:100%} figure{margin:1em 0;page-break-inside:avoid} figcaption{font-size:.9em;color:#444;max-width:52em}
.verdict{font-size:1.2em;font-weight:bold;padding:.5em .8em;border-radius:4px;margin:.6em 0}
.verdict.pass{background:#e3f4e3;color:#075f07} .verdict.remark{background:#fff3d6;color:#6b4b00}
.verdict.fail{background:#fbe3e3;color:#8a0000}
td.pass{color:#075f07;font-weight:bold} td.remark{color:#6b4b00;font-weight:bold} td.fail{color:#8a0000;font-weight:bold}
.program td,.program th{padding:.35em .7em} .program{font-size:1.02em}
.program td:nth-child(3),.program td:nth-child(5){white-space:nowrap}
.muted{color:#666;font-size:.9em}
@media print{body{margin:0;max-width:none} h2{page-break-after:avoid}}
"""


@dataclass(frozen=True)
class KeyValues:
    """A two-column table: a name and its value per row."""

    caption: str
    rows: Sequence[tuple[str, object]]


@dataclass(frozen=True)
class Grid:
    """A table with a header row; ``classes`` gives a CSS class per cell (``""`` for none)."""

    caption: str
    header: Sequence[str]
    rows: Sequence[Sequence[object]]
    classes: Sequence[Sequence[str]] = ()
    css: str = ""


@dataclass(frozen=True)
class Figure:
    """A PNG with the sentence that says what it shows."""

    caption: str
    png: bytes


@dataclass
class Section:
    """A titled part of the page; ``level`` 2 for the main parts, 3 inside them."""

    title: str
    blocks: list[str | KeyValues | Grid | Figure] = field(default_factory=list)
    level: int = 2


@dataclass(frozen=True)
class Verdict:
    """The overall verdict: :data:`PASS`, :data:`REMARK` or :data:`FAIL`, and one sentence."""

    status: str
    sentence: str


def fmt(value: object) -> str:
    """A cell's text: floats to 6 significant digits, NaN as a dash."""
    if isinstance(value, float):
        if math.isnan(value):
            return "–"
        return f"{value:.6g}" if math.isfinite(value) else ("∞" if value > 0 else "-∞")
    return str(value)


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _img(figure: Figure) -> str:
    data = base64.b64encode(figure.png).decode("ascii")
    cap = html.escape(figure.caption)
    return (
        f'<figure><img alt="{cap}" src="data:image/png;base64,{data}">'
        f"<figcaption>{cap}</figcaption></figure>"
    )


def _key_values(block: KeyValues) -> str:
    body = "".join(
        f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(fmt(v))}</td></tr>" for k, v in block.rows
    )
    head = f"<caption>{html.escape(block.caption)}</caption>" if block.caption else ""
    return f"<table>{head}{body}</table>"


def _grid(block: Grid) -> str:
    head = f"<caption>{html.escape(block.caption)}</caption>" if block.caption else ""
    cols = "".join(f"<th>{html.escape(h)}</th>" for h in block.header)
    rows = []
    for i, row in enumerate(block.rows):
        classes = block.classes[i] if i < len(block.classes) else ()
        cells = []
        for j, value in enumerate(row):
            css = " ".join(c for c in (classes[j] if j < len(classes) else "", "num" if _is_number(value) else "") if c)
            attr = f' class="{css}"' if css else ""
            cells.append(f"<td{attr}>{html.escape(fmt(value))}</td>")
        rows.append("<tr>" + "".join(cells) + "</tr>")
    css = f' class="{block.css}"' if block.css else ""
    return f"<table{css}>{head}<thead><tr>{cols}</tr></thead><tbody>{''.join(rows)}</tbody></table>"


def _block(block: str | KeyValues | Grid | Figure) -> str:
    if isinstance(block, str):
        return f"<p>{html.escape(block)}</p>"
    if isinstance(block, KeyValues):
        return _key_values(block)
    if isinstance(block, Grid):
        return _grid(block)
    return _img(block)


def render(
    title: str,
    verdict: Verdict,
    identity: KeyValues,
    sections: Sequence[Section],
    footer: str = "",
) -> str:
    """The whole page as text."""
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{html.escape(title)}</title><style>{_STYLE}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f'<div class="verdict {verdict.status}" id="verdict">{html.escape(verdict.sentence)}</div>',
        _key_values(identity),
    ]
    for s in sections:
        level = min(max(s.level, 2), 4)
        parts.append(f"<h{level}>{html.escape(s.title)}</h{level}>")
        parts.extend(_block(b) for b in s.blocks)
    if footer:
        parts.append(f'<p class="muted">{html.escape(footer)}</p>')
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"


def png_files(paths: Iterable[Path], captions: dict[str, str] | None = None) -> list[Figure]:
    """Figures of the existing PNG files, captioned from ``captions`` by file name.

    A file without a caption is described by its name as a sentence
    (``residual_spectrum.png`` -> "Residual spectrum.").
    """
    out = []
    for p in paths:
        if p.suffix.lower() == ".png" and p.is_file():
            caption = (captions or {}).get(p.name) or p.stem.replace("_", " ").capitalize() + "."
            out.append(Figure(caption, p.read_bytes()))
    return out


def write_report(path: Path, page: str) -> Path:
    """Write the page text (:func:`render`) to ``path``."""
    path.write_text(page, encoding="utf-8")
    return path
