"""The servobench log format: read and write, streaming.

Layout::

    # fs = 1000                  <- optional '# key = value' metadata lines
    # drive = sim://?M=0.1
    run,t,u,v,x                  <- CSV header, columns in any order, extras allowed
    1,0.000,5.0,0.0,0.0
    ...
    # status = complete          <- trailer written when the run ends

``run`` is optional for a single run (run 1 is the u1 experiment, run 2 the
u2 experiment); ``v`` or ``x`` may be missing, not both. ``t`` is in
seconds and never decreases within a run (equal consecutive instants are a
drive's repeated sample: two reads within one tick of its clock), ``u`` in
command units, ``v`` in velocity units/s, ``x`` in position units.
Closed-loop logs (metadata ``loop = closed``) also carry ``u_exc``, the
excitation (``u`` is then the total command applied, the hold loop's
included), and ``x_ref``, the position the hold loop holds.
Metadata lines may also follow the data (the writer appends
a trailer with the status and timing statistics; a later line wins). The
writer opens every log with ``# status = running``, so a log whose writer
died before the trailer (a killed host) reads as incomplete; a log without
any ``status`` line (written by other tools) is taken as complete. Lines end
in ``\n``, ``\r\n`` or ``\r``; a last line without its line break is a row
cut short by a crash, and is dropped (the log then reads as incomplete).

Files of other tools: a header whose separator is ``;`` (or a tab) and
numbers with a decimal comma are read as they are (see
:mod:`servobench.bench.log.table`); header names of other tools are mapped to
the signals with ``columns="t=Time,u=Input,v=Velocity,x=Position"``, the
syntax of ``.mat`` variable mappings (:mod:`servobench.bench.log.mapping`).

MATLAB ``.mat`` files are read with a variable mapping such as
``t=t,u=vir*gtau,x=qm`` (a factor may be a number or a scalar variable);
without one, a file lacking variables ``t`` and ``u`` answers with the
variables it holds.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from servobench.bench.log.mapping import (
    CLOSED_LOOP_SIGNALS,
    REQUIRED,
    SIGNALS,
    apply_map,
    format_map,
    parse_map,
    read_mat,
    sources,
)
from servobench.bench.log.table import parse_table, show
from servobench.errors import LogFormatError, one_line
from servobench.units import SignalUnits

__all__ = [
    "REQUIRED", "SIGNALS", "CLOSED_LOOP_SIGNALS", "MAX_RUN", "RunData", "ExperimentLog", "LogWriter",
    "read_log", "parse_log_text", "parse_map", "parse_mat_map",
]  # fmt: skip

#: Largest run number accepted [-].
MAX_RUN = 2**31 - 1
_KEY_BAD = re.compile(r"[^\w.\-]")


@dataclass(frozen=True)
class RunData:
    """One experiment run; arrays of shape ``(n,)``.

    Attributes
    ----------
    run : int
        Run number (1 = u1 experiment, 2 = u2 experiment).
    t : ndarray
        Sample times [s], never decreasing (equal: a drive's repeated sample).
    u : ndarray
        Applied command [command units], held over ``[t_k, t_k+1)``; in a
        closed-loop log the total command, the hold loop's included.
    v, x : ndarray or None
        Measured velocity [units/s] and position [units], sampled at ``t_k``.
    extra : dict of ndarray
        Any other columns.
    u_exc : ndarray or None
        Closed loop: the excitation [command units], held like ``u`` (the
        instrument of the closed-loop estimators); None in open loop.
    x_ref : ndarray or None
        Closed loop: the position the hold loop holds [units]; None in open loop.
    """

    run: int
    t: np.ndarray
    u: np.ndarray
    v: np.ndarray | None = None
    x: np.ndarray | None = None
    extra: Mapping[str, np.ndarray] = field(default_factory=dict)
    u_exc: np.ndarray | None = None
    x_ref: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = self.t.shape[0]
        for name in ("u", "v", "x", "u_exc", "x_ref"):
            arr = getattr(self, name)
            if arr is not None and arr.shape != (n,):
                raise LogFormatError(
                    f"run {self.run}: column {name} has {arr.shape} samples, t has {n}"
                )
        if self.v is None and self.x is None:
            raise LogFormatError(f"run {self.run}: the log needs a v or an x column")

    def __len__(self) -> int:
        return int(self.t.shape[0])


@dataclass(frozen=True)
class ExperimentLog:
    """A parsed log: runs in file order, metadata, sample rate [Hz]."""

    runs: tuple[RunData, ...]
    metadata: Mapping[str, str]
    fs_hz: float
    complete: bool = True
    source: str = ""

    @property
    def units(self) -> SignalUnits:
        """The units of ``u``, ``v`` and ``x`` its ``unit_*`` metadata states."""
        return SignalUnits.from_metadata(self.metadata)

    def run(self, number: int) -> RunData:
        for r in self.runs:
            if r.run == number:
                return r
        raise LogFormatError(f"{self.source or 'log'} has no run {number}")


# --------------------------------------------------------------------- writing
class LogWriter:
    """Write a log as samples arrive: every :meth:`append` reaches the OS at once.

    A crash loses at most the sample being written; :meth:`finish` appends the
    ``status`` trailer. Use as a context manager: leaving it on an exception
    marks the log incomplete with the reason.

    Parameters
    ----------
    path : path-like
        Output file (its folder must exist).
    metadata : mapping
        Written as ``# key = value`` lines before the header.
    columns : sequence of str
        CSV columns; the default is ``run,t,u,v,x``.
    flush_every : int
        Rows between flushes to the OS (1 = every sample).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        metadata: Mapping[str, object] | None = None,
        columns: tuple[str, ...] = SIGNALS,
        flush_every: int = 1,
    ) -> None:
        self.path = Path(path)
        self.columns = tuple(columns)
        self.flush_every = max(1, int(flush_every))
        self._pending = 0
        self.rows = 0
        self.status: str | None = None
        self._fh = open(self.path, "w", encoding="utf-8", newline="\n")  # noqa: SIM115
        meta = dict(metadata or {})
        meta.setdefault("status", "running")  # until the trailer says otherwise
        for key, value in meta.items():
            self._fh.write(f"# {_meta_key(key)} = {_meta_text(value)}\n")
        self._fh.write(",".join(self.columns) + "\n")
        self._fh.flush()

    def append(self, *values: float) -> None:
        """Append one row (values in column order)."""
        self._fh.write(",".join(_num(v) for v in values) + "\n")
        self.rows += 1
        self._pending += 1
        if self._pending >= self.flush_every:
            self._fh.flush()
            self._pending = 0

    def append_block(self, *columns: np.ndarray) -> None:
        """Append many rows at once (arrays in column order), then flush."""
        block = np.column_stack([np.asarray(c, dtype=float) for c in columns])
        row = ",".join(["%.10g"] * block.shape[1]) + "\n"
        self._fh.write((row * block.shape[0]) % tuple(block.ravel().tolist()))
        self._fh.flush()
        self.rows += block.shape[0]
        self._pending = 0

    def note(self, **metadata: object) -> None:
        """Append ``# key = value`` lines (e.g. timing statistics) after the data."""
        for key, value in metadata.items():
            self._fh.write(f"# {_meta_key(key)} = {_meta_text(value)}\n")
        self._fh.flush()

    def finish(self, status: str = "complete", reason: str = "", **metadata: object) -> None:
        """Write the trailer and close. ``status`` is ``complete`` or ``incomplete``."""
        if self._fh.closed:
            return
        self.note(**metadata)
        if reason:
            self.note(reason=reason)
        self.note(status=status)
        self.status = status
        self._fh.close()

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.finish("complete")
        else:
            reason = "interrupted (Ctrl-C)" if exc_type is KeyboardInterrupt else str(exc)
            self.finish("incomplete", reason=reason or exc_type.__name__)


def _num(value: float) -> str:
    return format(float(value), ".10g")


def _meta_text(value: object) -> str:
    if isinstance(value, (list, tuple, np.ndarray)):
        return ",".join(_meta_text(v) for v in value)
    if isinstance(value, float):
        return format(value, ".10g")
    return one_line(str(value)).strip()


def _meta_key(key: object) -> str:
    """A key the reader parses back: ``[A-Za-z_][\\w.-]*``."""
    text = _KEY_BAD.sub("_", str(key)) or "_"
    return text if re.match(r"[A-Za-z_]", text) else "_" + text


# --------------------------------------------------------------------- reading
def read_log(
    path: str | os.PathLike[str],
    mat_map: str | Mapping[str, str] | None = None,
    *,
    columns: str | Mapping[str, str] | None = None,
) -> ExperimentLog:
    """Read a servobench CSV log (or a CSV of another tool) or a MATLAB ``.mat`` file.

    Parameters
    ----------
    path : path-like
        The log.
    mat_map, columns : str or mapping, optional
        Which column or variable holds each signal, ``"t=Time,u=Input*35.15,x=Position"``
        (see :mod:`servobench.bench.log.mapping`); the two names are one option, for
        ``.mat`` variables and CSV columns alike. Without it, CSV columns and
        ``.mat`` variables named ``run``, ``t``, ``u``, ``v``, ``x`` are used.

    Raises
    ------
    LogFormatError
        Missing file, malformed content, missing columns.
    """
    spec = _one_mapping(mat_map, columns)
    path = Path(path)
    where = one_line(str(path))
    try:
        if not path.is_file():
            raise LogFormatError(f"no such log file: {where}")
        if path.suffix.lower() == ".mat":
            signals, used = read_mat(path, spec)
            metadata = {"source": f"{one_line(path.name)} (MATLAB)", "mat_map": used}
            return _assemble(signals, metadata, True, where)
        data = path.read_bytes()
    except OSError as err:
        raise LogFormatError(f"cannot read {where}: {err.strerror or err}") from None
    return parse_log_text(data, source=where, columns=spec)


def _one_mapping(mat_map, columns):
    if mat_map is not None and columns is not None and parse_map(mat_map) != parse_map(columns):
        raise LogFormatError("--mat-map and --columns disagree; give one mapping")
    return columns if columns is not None else mat_map


def parse_log_text(
    text: str | bytes,
    source: str = "log",
    columns: str | Mapping[str, str] | None = None,
    engine: str | None = None,
) -> ExperimentLog:
    """Parse the text of a CSV log, or its UTF-8 bytes (see the module docstring for the format).

    ``columns`` maps signals to header names (:mod:`servobench.bench.log.mapping`);
    ``engine`` forces the number reader (``"numpy"`` or ``"pyarrow"``, see
    :mod:`servobench.bench.log.table`).
    """
    source = one_line(source)
    mapping = parse_map(columns)
    table = parse_table(text, source, partial(_check_header, mapping=mapping, source=source), engine)
    named = dict(zip(table.header, table.columns, strict=True))
    metadata = dict(table.metadata)
    if mapping:
        used = sources(mapping)
        named = {k: v for k, v in named.items() if k not in used or k in mapping}
        named.update(apply_map(dict(zip(table.header, table.columns, strict=True)), mapping, source, "column"))
        metadata["columns"] = format_map(mapping)
    complete = metadata.get("status", "complete") == "complete" and not table.truncated
    return _assemble(named, metadata, complete, source)


def _check_header(header: list[str], mapping: Mapping[str, str], source: str) -> None:
    got = show(",".join(header))
    if len(set(header)) != len(header):
        raise LogFormatError(f"{source}: repeated column in header {got}")
    names = set(header)
    for signal, expr in mapping.items():
        for name in sorted(sources({signal: expr}) - names):
            raise LogFormatError(f"{source}: no column {name!r} for {signal} in header {got}")
    names = (names - sources(mapping)) | set(mapping)
    missing = [c for c in REQUIRED if c not in names]
    hint = "; name them with --columns t=NAME,u=NAME,v=NAME,x=NAME"
    if missing:
        raise LogFormatError(
            f"{source}: header lacks column(s) {', '.join(missing)} (got {got}){hint}"
        )
    if "v" not in names and "x" not in names:
        raise LogFormatError(f"{source}: header needs a v or an x column (got {got}){hint}")


def _assemble(
    columns: Mapping[str, np.ndarray], metadata: Mapping[str, str], complete: bool, source: str
) -> ExperimentLog:
    n = len(columns["t"])
    if n == 0:
        raise LogFormatError(f"{source}: the log holds no samples")
    for key, arr in columns.items():
        if len(arr) != n:
            raise LogFormatError(f"{source}: {key} has {len(arr)} samples, t has {n}")
        if not np.all(np.isfinite(arr)):
            raise LogFormatError(f"{source}: {key} holds a non-finite value")
    run_col = columns.get("run", np.ones(n))
    if np.any(run_col != np.round(run_col)) or np.any(np.abs(run_col) > MAX_RUN):
        raise LogFormatError(f"{source}: column run must hold integers (|run| <= {MAX_RUN})")
    runs: list[RunData] = []
    for number, idx in _run_rows(run_col):
        extra = {
            k: v[idx] for k, v in columns.items() if k not in SIGNALS + CLOSED_LOOP_SIGNALS
        }
        picked = {
            k: columns[k][idx] if k in columns else None for k in ("v", "x", *CLOSED_LOOP_SIGNALS)
        }
        runs.append(
            RunData(
                run=number,
                t=columns["t"][idx],
                u=columns["u"][idx],
                extra=extra,
                **picked,
            )
        )
    for r in runs:
        _check_time(r, source)
    fs_hz = _sample_rate(metadata, runs, source)
    return ExperimentLog(tuple(runs), dict(metadata), fs_hz, complete, source)


def _check_time(r: RunData, source: str) -> None:
    """A run's ``t`` must not decrease, and must advance over the run: equal consecutive
    instants are a drive's repeated sample (two reads within one tick of its clock)."""
    if len(r) < 2:
        return
    steps = np.diff(r.t)
    back = np.flatnonzero(steps < 0)
    if back.size:
        i = int(back[0]) + 1
        raise LogFormatError(
            f"{source}: run {r.run}: time stamps t are not increasing: t decreases at the run's "
            f"sample {i + 1} ({r.t[i - 1]:.10g} s, then {r.t[i]:.10g} s)"
        )
    if not r.t[-1] > r.t[0]:
        raise LogFormatError(f"{source}: run {r.run}: time stamps t are not increasing (all equal)")


def _run_rows(run_col: np.ndarray) -> list[tuple[int, slice | np.ndarray]]:
    """Each run number in file order with its rows: a slice when they are contiguous (as the
    writer leaves them), else a mask gathering the run's rows wherever they stand."""
    edges = np.flatnonzero(np.diff(run_col)) + 1
    starts = np.concatenate(([0], edges)).astype(int)
    ends = np.concatenate((edges, [len(run_col)])).astype(int)
    numbers = run_col[starts].astype(int).tolist()
    if len(set(numbers)) == len(numbers):
        return [(k, slice(a, b)) for k, a, b in zip(numbers, starts, ends, strict=True)]
    return [(k, run_col == k) for k in dict.fromkeys(numbers)]


def _sample_rate(metadata: Mapping[str, str], runs: list[RunData], source: str) -> float:
    if "fs" in metadata:
        try:
            fs = float(metadata["fs"])
        except ValueError:
            raise LogFormatError(
                f"{source}: metadata fs = {metadata['fs']!r} is not a number"
            ) from None
        if not (math.isfinite(fs) and fs > 0):
            raise LogFormatError(f"{source}: metadata fs must be > 0 Hz")
        return fs
    longest = max(runs, key=len)
    if len(longest) < 2:
        raise LogFormatError(
            f"{source}: cannot infer the sample rate from one sample; add '# fs = <Hz>'"
        )
    steps = np.diff(longest.t)
    with np.errstate(over="ignore", divide="ignore"):
        fs = float(1.0 / np.median(steps[steps > 0]))  # a repeated sample is no step
    if not math.isfinite(fs):
        raise LogFormatError(
            f"{source}: time steps too small to infer a sample rate; add '# fs = <Hz>'"
        )
    return fs


#: The mapping reader, under its first name.
parse_mat_map = parse_map
