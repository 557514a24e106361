"""The logs a fleet run takes: named files, and the logs found under named folders.

A named file is always taken. A named folder is searched recursively for
``*.csv`` files, in sorted path order, and every one is taken -- a garbled
log gets a row that says why it failed -- except the CSV files servobench
writes that are not identification logs:

- a fleet table (``fleet.csv``) and a diagnosis' ``comparison.csv``, known by their headers;
- a commissioning bump test (metadata ``experiment = bump test``);
- the rounds ``log-N.csv`` of a ``sidbe`` run folder, whose chosen round is
  copied to ``log.csv`` beside them (one record per run, not one per round).

A log named twice is taken once. The order is the order of the rows.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from servobench.bench.fleet.table import COLUMNS
from servobench.errors import UsageError, one_line

#: Lines read from the top of a CSV file to decide whether it is a log.
HEAD_LINES = 200
_META = re.compile(r"^#\s*([A-Za-z_][\w.\-]*)\s*=\s*(.*?)\s*$")
#: Metadata ``experiment`` values that are not identification runs.
NOT_IDENTIFICATION = frozenset({"bump test"})
#: Headers of the CSV tables servobench writes that are not logs.
_NOT_LOG_HEADERS = frozenset({COLUMNS, ("run", "t", "v_measured", "v_before", "v_after")})
#: A round of a ``sidbe`` run folder.
_ROUND = re.compile(r"log-\d+\.csv")


@dataclass(frozen=True)
class LogSource:
    """A log to process: ``name`` as shown in the table, ``path`` absolute (what a worker opens)."""

    name: str
    path: str


def find_logs(items: Iterable[str | os.PathLike[str]]) -> list[LogSource]:
    """The logs named by ``items`` (files and folders), in order, each once.

    Raises
    ------
    UsageError
        A named path does not exist, or nothing names a log.
    """
    items = list(items)
    seen: set[str] = set()
    out: list[LogSource] = []
    for item in items:
        path = Path(item)
        if path.is_dir():
            found = [p for p in sorted(path.rglob("*.csv")) if p.is_file() and not skipped(p)]
        elif path.exists():
            found = [path]
        else:
            raise UsageError(f"no such log file or folder: {one_line(str(path))}")
        for p in found:
            absolute = str(p.resolve())
            if absolute not in seen:
                seen.add(absolute)
                out.append(LogSource(str(p), absolute))
    if not out:
        named = ", ".join(one_line(str(i)) for i in items) or "nothing"
        raise UsageError(
            f"no servobench log found in {named}: name CSV logs or folders holding them"
        )
    return out


def skipped(path: Path) -> bool:
    """True for a CSV file in a searched folder that is not an identification log (see above)."""
    if _ROUND.fullmatch(path.name) and (path.parent / "log.csv").is_file():
        return True
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            for _, line in zip(range(HEAD_LINES), fh, strict=False):
                text = line.strip().removeprefix("\ufeff")
                if not text:
                    continue
                if text.startswith("#"):
                    m = _META.match(text)
                    if m and m.group(1) == "experiment" and m.group(2) in NOT_IDENTIFICATION:
                        return True
                    continue
                header = tuple(h.strip() for h in text.split(","))
                return header in _NOT_LOG_HEADERS
    except OSError:
        return False  # taken, so that its row says why it cannot be read
    return False
