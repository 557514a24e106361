"""The text of a CSV log, parsed: metadata lines, the header and the table of numbers.

The format is described in :mod:`servobench.bench.log.io`. Parsing takes two
passes over the text, neither of them one Python step per row:

1. structure, with ``str.find``: the ``#`` metadata lines (before, between
   and after the data), the header, and the data rows between them;
2. numbers: the data rows handed whole to a C CSV reader -- ``pyarrow.csv``
   for large tables when pyarrow is installed (the ``fleet`` extra), else
   ``numpy.loadtxt``.

Separators: ``,`` by default; ``;`` when the header holds one, and a tab
when the header holds tabs and no comma. With ``;`` or a tab, numbers may
carry a decimal comma (``0,25``), as spreadsheets in many locales write them.

Whatever the C reader does not take cleanly -- a ragged row, a malformed or
non-finite number, a ``#`` inside a row, a line break other than CR/LF --
sends the text through :func:`checked_parse`, the line-by-line reference
that names the line and what is wrong with it. The fast pass only ever
returns what the reference returns.
"""

from __future__ import annotations

import io
import re
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from servobench.errors import LogFormatError, one_line

#: Bodies longer than this [characters] go to pyarrow when it is installed.
PYARROW_MIN_CHARS = 1_000_000
#: Engines :func:`parse_table` knows; ``None`` picks by size and availability.
ENGINES = ("numpy", "pyarrow")

_META = re.compile(r"^#\s*([A-Za-z_][\w.\-]*)\s*=\s*(.*?)\s*$")
_LINE_BREAK = re.compile(r"\r\n|\r|\n")
#: Line breaks other than CR/LF (vertical tab, form feed, separators, ...): never in a data row.
ODD_BREAKS = "\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029"
_ODD_BREAK = re.compile(f"[{ODD_BREAKS}]")

HeaderCheck = Callable[[list[str]], None]


@dataclass(frozen=True)
class Table:
    """A parsed CSV log before its columns are interpreted.

    Attributes
    ----------
    metadata : dict of str
        ``# key = value`` lines, wherever they stand; a later line wins.
    header : list of str
        Column names as written (whitespace and double quotes stripped).
    columns : list of ndarray
        One array of shape ``(rows,)`` per header name, finite floats.
    truncated : bool
        The text ended inside a row, which was dropped (a crash mid-write).
    """

    metadata: dict[str, str]
    header: list[str]
    columns: list[np.ndarray]
    truncated: bool


def show(text: str, limit: int = 60) -> str:
    """A short, one-line rendering of untrusted text for an error message."""
    shown = repr(text[:limit])
    return shown + ("..." if len(text) > limit else "")


def delimiter_of(header_line: str) -> str:
    """The separator a header line uses: ``;``, a tab, or ``,``."""
    if ";" in header_line:
        return ";"
    if "\t" in header_line and "," not in header_line:
        return "\t"
    return ","


def split_header(line: str, delimiter: str) -> list[str]:
    return [h.strip().strip('"').strip() for h in line.split(delimiter)]


def parse_table(
    text: str | bytes, source: str, check_header: HeaderCheck, engine: str | None = None
) -> Table:
    """Parse a CSV log (text, or its UTF-8 bytes); ``check_header(names)`` raises for a header
    it cannot use.

    Raises
    ------
    LogFormatError
        Bytes that are not UTF-8, no header, no data rows, a ragged row, a malformed or
        non-finite number, a control character in a row, or whatever ``check_header`` raises.
    """
    if engine is not None and engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES}, got {engine!r}")
    if isinstance(text, bytes) and not text.isascii():
        try:
            text = text.decode("utf-8")
        except UnicodeDecodeError:
            raise LogFormatError(f"{source} is not a text log (not UTF-8)") from None
    if isinstance(text, str):
        text = text.removeprefix("\ufeff")  # a byte-order mark from a spreadsheet
    # ASCII bytes stay bytes: the structure pass works on either, the C readers take bytes
    nl, cr = _lit(text, "\n"), _lit(text, "\r")
    truncated = bool(text) and not text.endswith((nl, cr))
    if cr in text:
        text = text.replace(cr + nl, nl).replace(cr, nl)
    if truncated:  # a crash mid-write: the last partial row is dropped
        text = text[: text.rfind(nl) + 1]
    # one substring search per character: far faster than a regex class over a long text
    odd = any(_lit(text, c) in text for c in ODD_BREAKS if isinstance(text, str) or c.isascii())
    fast = None if odd else _fast_parse(text, source, check_header, engine)
    if fast is not None:
        return Table(fast[0], fast[1], fast[2], truncated)
    lines = (text if isinstance(text, str) else text.decode("ascii")).split("\n")
    metadata, header, columns = checked_parse(lines, source, check_header)
    return Table(metadata, header, columns, truncated)


def _lit(text: str | bytes, literal: str) -> str | bytes:
    """``literal`` as the same type as ``text`` (an ASCII literal for bytes)."""
    return literal if isinstance(text, str) else literal.encode("ascii")


def _str(text: str | bytes) -> str:
    return text if isinstance(text, str) else text.decode("ascii")


# ------------------------------------------------------------------ fast pass
def _fast_parse(text: str | bytes, source: str, check_header: HeaderCheck, engine: str | None):
    """``(metadata, header, columns)``, or None when the reference must decide."""
    header_start, header_end = _header_span(text)
    comments, stray = _comment_lines(text)
    if stray or header_start < 0:
        return None
    metadata: dict[str, str] = {}
    for start, end in comments:
        m = _META.match(_str(text[start:end]).strip())
        if m:
            metadata[m.group(1)] = m.group(2)
    line = _str(text[header_start:header_end])
    delimiter = delimiter_of(line)
    header = split_header(line, delimiter)
    check_header(header)
    pieces, at = [], header_end
    for start, end in comments:
        if start >= at:
            pieces.append(text[at:start])
            at = end
    pieces.append(text[at:])
    body = _lit(text, "").join(pieces)
    if not body or body.isspace():
        raise LogFormatError(f"{source}: no data rows")
    if delimiter != ",":
        body = body.replace(_lit(body, ","), _lit(body, "."))
    columns = _numbers(body, len(header), delimiter, engine)
    return None if columns is None else (metadata, header, columns)


def _header_span(text: str | bytes) -> tuple[int, int]:
    """Start and end (after its line break) of the first line that is neither blank nor a comment."""
    nl, hash_ = _lit(text, "\n"), _lit(text, "#")
    pos = 0
    while pos < len(text):
        end = text.find(nl, pos)
        end = len(text) if end < 0 else end + 1
        line = text[pos:end].strip()
        if line and not line.startswith(hash_):
            return pos, end
        pos = end
    return -1, -1


def _comment_lines(text: str | bytes) -> tuple[list[tuple[int, int]], bool]:
    """Spans of the lines that start with ``#``, and whether a ``#`` stands inside another line."""
    nl, hash_ = _lit(text, "\n"), _lit(text, "#")
    spans: list[tuple[int, int]] = []
    stray = False
    pos = text.find(hash_)
    while pos >= 0:
        start = text.rfind(nl, 0, pos) + 1
        end = text.find(nl, pos)
        end = len(text) if end < 0 else end + 1
        if text[start:pos].strip():
            stray = True
        else:
            spans.append((start, end))
        pos = text.find(hash_, end)
    return spans, stray


def _numbers(
    body: str | bytes, width: int, delimiter: str, engine: str | None
) -> list[np.ndarray] | None:
    """The columns of the data rows, or None unless every row holds ``width`` finite numbers."""
    if engine is None:
        engine = "pyarrow" if len(body) >= PYARROW_MIN_CHARS and _pyarrow_csv() else "numpy"
    try:
        if engine == "pyarrow":
            columns = _read_pyarrow(body, width, delimiter)
        else:
            data = np.loadtxt(io.StringIO(_str(body)), delimiter=delimiter, ndmin=2, comments=None)
            columns = list(np.ascontiguousarray(data.T)) if data.shape[1] == width else None
    except (ValueError, TypeError, ArithmeticError):  # pyarrow raises ValueError and TypeError kinds
        return None
    if columns is None or not all(np.isfinite(c).all() for c in columns):
        return None
    return columns


def _pyarrow_csv():
    try:
        import pyarrow.csv as pacsv
    except ImportError:
        return None
    return pacsv


def _read_pyarrow(body: str | bytes, width: int, delimiter: str) -> list[np.ndarray] | None:
    pacsv = _pyarrow_csv()
    if pacsv is None:
        raise ValueError("pyarrow is not installed (pip install 'servobench[fleet]')")
    import pyarrow as pa

    names = [f"c{i}" for i in range(width)]
    table = pacsv.read_csv(
        pa.py_buffer(body if isinstance(body, bytes) else body.encode("utf-8")),
        # one thread: Arrow's thread pool, torn down at interpreter exit with a worker still
        # alive, aborts the process ("terminate called without an active exception", exit -6,
        # apache/arrow#34314), once seen after a complete sidbe run
        read_options=pacsv.ReadOptions(column_names=names, block_size=1 << 22, use_threads=False),
        parse_options=pacsv.ParseOptions(delimiter=delimiter, quote_char=False),
        convert_options=pacsv.ConvertOptions(column_types=dict.fromkeys(names, pa.float64())),
    )
    if any(col.null_count for col in table.columns):
        return None
    return [col.to_numpy() for col in table.columns]


# ------------------------------------------------------------- the reference
def checked_parse(
    lines: list[str], source: str, check_header: HeaderCheck
) -> tuple[dict[str, str], list[str], list[np.ndarray]]:
    """Parse line by line and name the first line that breaks the format.

    ``lines`` are split at CR/LF only (the partial last row already dropped);
    other line breaks inside a data row are an error.
    """
    metadata: dict[str, str] = {}
    header: list[str] | None = None
    delimiter = ","
    rows: list[str] = []
    for lineno, raw in enumerate(lines, start=1):
        line = raw.strip()
        if not line:
            continue
        if line.startswith("#"):
            m = _META.match(line)
            if m:
                metadata[m.group(1)] = m.group(2)
            continue
        if header is None:
            delimiter = delimiter_of(line)
            header = split_header(line, delimiter)
            check_header(header)
            continue
        rows.append(line)
        if line.count(delimiter) != len(header) - 1:
            raise LogFormatError(
                f"{source}:{lineno}: expected {len(header)} fields, got {line.count(delimiter) + 1}"
            )
    if header is not None:
        _check_odd_breaks(lines, header, delimiter, source)
    if header is None:
        raise LogFormatError(f"{source}: no CSV header (expected columns like run,t,u,v,x)")
    if not rows:
        raise LogFormatError(f"{source}: no data rows")
    body = "\n".join(rows)
    if delimiter != ",":
        body = body.replace(",", ".")
    try:
        data = np.loadtxt(io.StringIO(body), delimiter=delimiter, ndmin=2)
    except ValueError as err:
        raise LogFormatError(f"{source}: malformed number in data ({one_line(str(err))})") from None
    if not np.all(np.isfinite(data)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(data), axis=1))[0])
        raise LogFormatError(f"{source}: data row {bad + 1} holds a non-finite value")
    return metadata, header, list(np.ascontiguousarray(data.T))


def _check_odd_breaks(lines: list[str], header: list[str], delimiter: str, source: str) -> None:
    """A line break other than CR/LF inside a data row is an error naming its line."""
    joined = delimiter.join(header)
    for index, row in enumerate(lines):
        if _ODD_BREAK.search(row) and not row.lstrip().startswith("#") and row.strip() != joined:
            raise LogFormatError(f"{source}:{index + 1}: control character in row {show(row)}")
