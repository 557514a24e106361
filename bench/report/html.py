"""``report.html``: one self-contained page, the plots embedded as base64 PNG.

No external files, scripts or style sheets: the page can be mailed or
archived as is. Sections: the drive and the limits, the bump test, the
identified model with uncertainties, excitation, velocities, frequency
response, friction map, the diagnosis before/after, and the suggested
compensation and PI with their simulation check.
"""

from __future__ import annotations

import base64
import html
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

REPORT_FILE = "report.html"

_STYLE = """
body{font-family:sans-serif;max-width:60em;margin:2em auto;color:#222}
h1{font-size:1.5em} h2{font-size:1.2em;border-bottom:1px solid #ccc;margin-top:2em}
table{border-collapse:collapse;margin:.5em 0} td,th{border:1px solid #ccc;padding:.2em .6em;text-align:left}
img{max-width:100%} .bad{color:#a00} .ok{color:#070} figure{margin:1em 0} figcaption{font-size:.9em;color:#555}
"""


@dataclass
class Section:
    """A report section: a title, paragraphs, key/value tables and figures (PNG bytes)."""

    title: str
    paragraphs: list[str] = field(default_factory=list)
    tables: list[tuple[str, Sequence[tuple[str, object]]]] = field(default_factory=list)
    figures: list[tuple[str, bytes]] = field(default_factory=list)


def _fmt(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.6g}" if math.isfinite(value) else str(value)
    return str(value)


def _img(caption: str, png: bytes) -> str:
    data = base64.b64encode(png).decode("ascii")
    cap = html.escape(caption)
    return (
        f'<figure><img alt="{cap}" src="data:image/png;base64,{data}">'
        f"<figcaption>{cap}</figcaption></figure>"
    )


def _table(title: str, rows: Iterable[tuple[str, object]]) -> str:
    body = "".join(
        f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(_fmt(v))}</td></tr>" for k, v in rows
    )
    head = f"<caption>{html.escape(title)}</caption>" if title else ""
    return f"<table>{head}{body}</table>"


def render(title: str, status: str, sections: Sequence[Section], meta: Mapping[str, str]) -> str:
    """The whole page as text."""
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{html.escape(title)}</title><style>{_STYLE}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f'<p class="{"ok" if status == "complete" else "bad"}">Status: {html.escape(status)}</p>',
        _table("", meta.items()),
    ]
    for s in sections:
        parts.append(f"<h2>{html.escape(s.title)}</h2>")
        parts.extend(f"<p>{html.escape(p)}</p>" for p in s.paragraphs)
        parts.extend(_table(t, rows) for t, rows in s.tables)
        parts.extend(_img(c, png) for c, png in s.figures)
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"


def png_files(paths: Iterable[Path]) -> list[tuple[str, bytes]]:
    """``(caption, bytes)`` of existing PNG files, caption from the file name."""
    out = []
    for p in paths:
        if p.suffix.lower() == ".png" and p.is_file():
            out.append((p.stem.replace("_", " "), p.read_bytes()))
    return out


def write_report(path: Path, title: str, status: str, sections: Sequence[Section], meta: Mapping[str, str]) -> Path:
    path.write_text(render(title, status, sections, meta), encoding="utf-8")
    return path
