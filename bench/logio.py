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
seconds, ``u`` in command units, ``v`` in velocity units/s, ``x`` in
position units. Metadata lines may also follow the data (the writer appends
a trailer with the status and timing statistics; a later line wins). The
writer opens every log with ``# status = running``, so a log whose writer
died before the trailer (a killed host) reads as incomplete; a log without
any ``status`` line (written by other tools) is taken as complete. Lines end
in ``\n``, ``\r\n`` or ``\r``.

MATLAB ``.mat`` files are read with a variable mapping such as
``t=t,u=vir*gtau,x=qm`` (a factor may be a number or a scalar variable).
"""

from __future__ import annotations

import io
import math
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from servobench.errors import LogFormatError, one_line
from servobench.units import SignalUnits

REQUIRED = ("t", "u")
SIGNALS = ("run", "t", "u", "v", "x")
#: Largest run number accepted [-].
MAX_RUN = 2**31 - 1
_META = re.compile(r"^#\s*([A-Za-z_][\w.\-]*)\s*=\s*(.*?)\s*$")
_KEY_BAD = re.compile(r"[^\w.\-]")
_LINE_BREAK = re.compile(r"\r\n|\r|\n")
#: Line breaks other than CR/LF (vertical tab, form feed, separators, ...): never in a data row.
_ODD_BREAK = re.compile("[\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029]")


def _show(text: str, limit: int = 60) -> str:
    """A short, one-line rendering of untrusted text for an error message."""
    shown = repr(text[:limit])
    return shown + ("..." if len(text) > limit else "")


@dataclass(frozen=True)
class RunData:
    """One experiment run; arrays of shape ``(n,)``.

    Attributes
    ----------
    run : int
        Run number (1 = u1 experiment, 2 = u2 experiment).
    t : ndarray
        Sample times [s].
    u : ndarray
        Applied command [command units], held over ``[t_k, t_k+1)``.
    v, x : ndarray or None
        Measured velocity [units/s] and position [units], sampled at ``t_k``.
    extra : dict of ndarray
        Any other columns.
    """

    run: int
    t: np.ndarray
    u: np.ndarray
    v: np.ndarray | None = None
    x: np.ndarray | None = None
    extra: Mapping[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = self.t.shape[0]
        for name in ("u", "v", "x"):
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
    path: str | os.PathLike[str], mat_map: str | Mapping[str, str] | None = None
) -> ExperimentLog:
    """Read a servobench CSV log or a MATLAB ``.mat`` file.

    Parameters
    ----------
    path : path-like
        The log.
    mat_map : str or mapping, optional
        For ``.mat`` files: ``"t=t,u=vir*gtau,x=qm"`` or ``{"u": "vir*gtau", ...}``.
        Without it, variables named ``t``, ``u``, ``v``, ``x`` (and ``run``) are used.

    Raises
    ------
    LogFormatError
        Missing file, malformed content, missing columns.
    """
    path = Path(path)
    where = one_line(str(path))
    try:
        if not path.is_file():
            raise LogFormatError(f"no such log file: {where}")
        if path.suffix.lower() == ".mat":
            return _read_mat(path, mat_map)
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise LogFormatError(f"{where} is not a text log (not UTF-8)") from None
    except OSError as err:
        raise LogFormatError(f"cannot read {where}: {err.strerror or err}") from None
    return parse_log_text(text, source=where)


def parse_log_text(text: str, source: str = "log") -> ExperimentLog:
    """Parse the text of a CSV log (see the module docstring for the format)."""
    source = one_line(source)
    metadata: dict[str, str] = {}
    header: list[str] | None = None
    rows: list[str] = []
    text = text.removeprefix("\ufeff")  # a byte-order mark from a spreadsheet
    truncated = bool(text) and not text.endswith(("\n", "\r"))
    lines = _LINE_BREAK.split(text)
    # Odd line breaks are searched once in the whole text, not row by row.
    odd_lines = sorted({len(_LINE_BREAK.findall(text, 0, m.start())) for m in _ODD_BREAK.finditer(text)})
    if truncated:
        lines = lines[:-1]  # a crash mid-write: the last partial row is dropped
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
            header = [h.strip() for h in line.split(",")]
            _check_header(header, source)
            continue
        rows.append(line)
        if line.count(",") != len(header) - 1:
            raise LogFormatError(
                f"{source}:{lineno}: expected {len(header)} fields, got {line.count(',') + 1}"
            )
    for index in (i for i in odd_lines if i < len(lines)):  # a dropped partial row is no row
        row = lines[index]
        if header is not None and not row.lstrip().startswith("#") and row.strip() != ",".join(header):
            raise LogFormatError(f"{source}:{index + 1}: control character in row {_show(row)}")
    if header is None:
        raise LogFormatError(f"{source}: no CSV header (expected columns like run,t,u,v,x)")
    if not rows:
        raise LogFormatError(f"{source}: no data rows")
    try:
        data = np.loadtxt(io.StringIO("\n".join(rows)), delimiter=",", ndmin=2)
    except ValueError as err:
        raise LogFormatError(f"{source}: malformed number in data ({one_line(str(err))})") from None
    if not np.all(np.isfinite(data)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(data), axis=1))[0])
        raise LogFormatError(f"{source}: data row {bad + 1} holds a non-finite value")
    columns = {name: data[:, i] for i, name in enumerate(header)}
    complete = metadata.get("status", "complete") == "complete" and not truncated
    return _assemble(columns, metadata, complete, source)


def _check_header(header: list[str], source: str) -> None:
    got = _show(",".join(header))
    if len(set(header)) != len(header):
        raise LogFormatError(f"{source}: repeated column in header {got}")
    missing = [c for c in REQUIRED if c not in header]
    if missing:
        raise LogFormatError(f"{source}: header lacks column(s) {', '.join(missing)} (got {got})")
    if "v" not in header and "x" not in header:
        raise LogFormatError(f"{source}: header needs a v or an x column (got {got})")


def _assemble(
    columns: Mapping[str, np.ndarray], metadata: Mapping[str, str], complete: bool, source: str
) -> ExperimentLog:
    n = len(columns["t"])
    run_col = columns.get("run", np.ones(n))
    if np.any(run_col != np.round(run_col)) or np.any(np.abs(run_col) > MAX_RUN):
        raise LogFormatError(f"{source}: column run must hold integers (|run| <= {MAX_RUN})")
    runs: list[RunData] = []
    for number in dict.fromkeys(run_col.astype(int).tolist()):
        idx = run_col == number
        extra = {k: v[idx] for k, v in columns.items() if k not in SIGNALS}
        runs.append(
            RunData(
                run=int(number),
                t=columns["t"][idx],
                u=columns["u"][idx],
                v=columns["v"][idx] if "v" in columns else None,
                x=columns["x"][idx] if "x" in columns else None,
                extra=extra,
            )
        )
    for r in runs:
        if len(r) >= 2 and not np.all(np.diff(r.t) > 0):
            raise LogFormatError(f"{source}: run {r.run}: time stamps t are not increasing")
    fs_hz = _sample_rate(metadata, runs, source)
    return ExperimentLog(tuple(runs), dict(metadata), fs_hz, complete, source)


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
    with np.errstate(over="ignore", divide="ignore"):
        fs = float(1.0 / np.median(np.diff(longest.t)))
    if not math.isfinite(fs):
        raise LogFormatError(
            f"{source}: time steps too small to infer a sample rate; add '# fs = <Hz>'"
        )
    return fs


def parse_mat_map(spec: str | Mapping[str, str] | None) -> dict[str, str]:
    """``"t=t,u=vir*gtau"`` -> ``{"t": "t", "u": "vir*gtau"}``."""
    if spec is None:
        return {}
    if isinstance(spec, Mapping):
        return dict(spec)
    out: dict[str, str] = {}
    for item in filter(None, (s.strip() for s in spec.split(","))):
        key, sep, expr = item.partition("=")
        if not sep or not key.strip() or not expr.strip():
            raise LogFormatError(f"bad variable mapping {item!r}; expected name=variable[*factor]")
        out[key.strip()] = expr.strip()
    return out


def _read_mat(path: Path, spec: str | Mapping[str, str] | None) -> ExperimentLog:
    from scipy.io import loadmat

    where = one_line(str(path))
    mapping_spec = parse_mat_map(spec)
    try:
        mat = loadmat(str(path), squeeze_me=True)
    except Exception as err:  # scipy raises several types for a bad file
        raise LogFormatError(
            f"{where}: not a readable MATLAB file ({one_line(str(err))[:200]})"
        ) from None
    mapping = mapping_spec or {k: k for k in SIGNALS if k in mat}

    def value(expr: str) -> np.ndarray | float:
        out: np.ndarray | float = 1.0
        for factor in expr.split("*"):
            factor = factor.strip()
            try:
                out = out * float(factor)
                continue
            except ValueError:
                pass
            if factor not in mat:
                raise LogFormatError(
                    f"{where}: no variable {factor!r} (has {', '.join(_mat_vars(mat))})"
                )
            try:
                out = out * np.asarray(mat[factor], dtype=float)
            except (TypeError, ValueError):
                raise LogFormatError(f"{where}: variable {factor!r} is not numeric") from None
        return out

    columns: dict[str, np.ndarray] = {}
    for key, expr in mapping.items():
        columns[key] = np.atleast_1d(np.asarray(value(expr), dtype=float)).ravel()
    missing = [c for c in REQUIRED if c not in columns]
    if missing:
        raise LogFormatError(
            f"{where}: mapping lacks {', '.join(missing)}; pass e.g. --mat-map t=t,u=vir*gtau,x=qm"
        )
    n = len(columns["t"])
    for key, arr in columns.items():
        if len(arr) != n:
            raise LogFormatError(f"{where}: variable for {key} has {len(arr)} samples, t has {n}")
        if not np.all(np.isfinite(arr)):
            raise LogFormatError(f"{where}: variable for {key} holds a non-finite value")
    if n == 0:
        raise LogFormatError(f"{where}: the variables hold no samples")
    metadata = {
        "source": f"{one_line(path.name)} (MATLAB)",
        "mat_map": ",".join(f"{k}={v}" for k, v in mapping.items()),
    }
    return _assemble(columns, metadata, True, where)


def _mat_vars(mat: Mapping[str, object]) -> list[str]:
    return sorted(k for k in mat if not k.startswith("__"))
