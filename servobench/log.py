"""``servobench.Log`` and ``servobench.read_log``: an experiment log, its runs as numpy arrays.

:class:`Log` *is* the log type every part of servobench reads
(:class:`servobench.bench.log.io.ExperimentLog`), with :meth:`Log.to_pandas`
added; :func:`read_log` is the CLI's reader (``identify``, ``diagnose`` and
``validate`` read their LOG with it), with the same messages.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from servobench.bench.log.io import ExperimentLog
from servobench.bench.log.io import read_log as _read_log

__all__ = ["Log", "read_log"]

#: Columns of :meth:`Log.to_pandas` before the extras, in order.
COLUMNS = ("run", "t", "u", "v", "x", "u_exc", "x_ref")


@dataclass(frozen=True)
class Log(ExperimentLog):
    """A parsed log: runs in file order, metadata, sample rate.

    Attributes
    ----------
    runs : tuple of RunData
        Each run's arrays, shape ``(n,)``: ``t`` [s], ``u`` [command units], ``v``
        [velocity units] and ``x`` [position units] (either may be None),
        closed-loop ``u_exc`` and ``x_ref``, and ``extra`` columns by name.
    metadata : mapping
        The log's ``# key = value`` lines (``fs``, ``drive``, ``unit_u`` ...).
    fs_hz : float
        Sample rate [Hz].
    complete : bool
        False when the writer did not finish (a killed run).
    source : str
        The file read.
    """

    @classmethod
    def of(cls, log: ExperimentLog) -> Log:
        """``log`` as a :class:`Log` (the same arrays, not copied)."""
        if isinstance(log, cls):
            return log
        return cls(**{f.name: getattr(log, f.name) for f in fields(ExperimentLog)})

    def to_pandas(self) -> Any:
        """One ``pandas.DataFrame`` of every run's samples, in file order.

        Columns ``run``, ``t``, ``u``, ``v``, ``x`` (and ``u_exc``, ``x_ref``, extras where the
        log has them; NaN in runs without them); ``attrs`` holds ``metadata``, ``fs_hz``
        [Hz] and ``source``.

        Raises
        ------
        ImportError
            pandas is not installed (it is no dependency of servobench).
        """
        try:
            import pandas as pd
        except ImportError:
            raise ImportError("Log.to_pandas needs pandas, which is not installed: pip install pandas") from None
        extras = list(dict.fromkeys(k for r in self.runs for k in r.extra))
        present = [c for c in COLUMNS[2:] if any(getattr(r, c) is not None for r in self.runs)]
        table: dict[str, list[np.ndarray]] = {c: [] for c in ("run", "t", *present, *extras)}
        for r in self.runs:
            n = len(r)
            table["run"].append(np.full(n, r.run, dtype=np.int64))
            table["t"].append(np.asarray(r.t, dtype=float))
            for c in present:
                value = getattr(r, c)
                table[c].append(np.full(n, np.nan) if value is None else np.asarray(value, dtype=float))
            for c in extras:
                table[c].append(np.asarray(r.extra[c], dtype=float) if c in r.extra else np.full(n, np.nan))
        frame = pd.DataFrame({c: np.concatenate(parts) if parts else np.zeros(0) for c, parts in table.items()})
        frame.attrs.update({"metadata": dict(self.metadata), "fs_hz": self.fs_hz, "source": self.source})
        return frame


def read_log(
    path: str | os.PathLike[str],
    *,
    columns: str | Mapping[str, str] | None = None,
    mat_map: str | Mapping[str, str] | None = None,
) -> Log:
    """Read a servobench CSV log, a CSV of another tool, or a MATLAB ``.mat`` file.

    Parameters
    ----------
    path : path-like
    columns, mat_map : str or mapping, optional
        Which column (CSV) or variable (``.mat``) holds each signal, e.g.
        ``"t=Time,u=Input*35.15,v=Velocity,x=Position"`` (the CLI's ``--columns`` and
        ``--mat-map``: one mapping, under either name).

    Raises
    ------
    LogFormatError
        Missing file, malformed content, missing columns (the CLI's message).
    """
    return Log.of(_read_log(path, mat_map, columns=columns))

