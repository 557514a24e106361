"""The fleet table: one row per log, written as ``fleet.csv`` and ``fleet.parquet``.

Columns, in this order (the contract of ``servobench fleet``)::

    log, axis, time, M, B, pole, dc_gain, coulomb_pos, coulomb_neg,
    fit_percent, method, effects, gap_before, gap_after, error,
    model, diagnosed_M, diagnosed_B, diagnosed_coulomb_pos, diagnosed_coulomb_neg

``time`` is ISO 8601 with its UTC offset; ``effects`` names the effects
``--diagnose`` added, separated by ``;``; ``gap_before``/``gap_after`` are
the diagnosis' velocity gaps [%]. A number that was not found (a failed
log, no ``--diagnose``) is empty in the CSV and null in Parquet. ``error``
is empty for a log that went through, else its one-line reason. ``M`` ...
``coulomb_neg`` are ``identify``'s base model; with ``--diagnose``,
``model`` names the diagnosed model's structure (``base``, ``base +
stribeck``) and ``diagnosed_*`` its base parameters, refitted together with
the effects. The trend compares like with like: the diagnosed parameters
where the diagnosis ran (:meth:`FleetRow.compared`), and says when the
structure changed between two records of an axis.

The units of each parameter depend on the log (``unit_*`` metadata) and
cannot live in a column of numbers: the Parquet file carries them per
axis in its schema metadata (key ``servobench.units``, a JSON object
``{axis: {parameter: unit}}``), and the trend page and ``--json`` show them.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

#: The columns of fleet.csv and fleet.parquet, in order.
COLUMNS = (
    "log", "axis", "time", "M", "B", "pole", "dc_gain", "coulomb_pos", "coulomb_neg",
    "fit_percent", "method", "effects", "gap_before", "gap_after", "error",
    "model", "diagnosed_M", "diagnosed_B", "diagnosed_coulomb_pos", "diagnosed_coulomb_neg",
)  # fmt: skip
#: The numeric columns.
NUMBERS = ("M", "B", "pole", "dc_gain", "coulomb_pos", "coulomb_neg", "fit_percent",
           "gap_before", "gap_after", "diagnosed_M", "diagnosed_B", "diagnosed_coulomb_pos",
           "diagnosed_coulomb_neg")  # fmt: skip
#: Base parameters the diagnosis refits (its ``diagnosed_*`` columns).
DIAGNOSED = ("M", "B", "coulomb_pos", "coulomb_neg")
#: Separator of effect names in the ``effects`` column.
EFFECT_SEPARATOR = ";"
CSV_FILE = "fleet.csv"
PARQUET_FILE = "fleet.parquet"
#: Parquet schema-metadata key of the units per axis.
UNITS_KEY = b"servobench.units"

NAN = math.nan


@dataclass(frozen=True)
class FleetRow:
    """One log's outcome; numbers are NaN where not found.

    Attributes
    ----------
    log : str
        The log's path as the user named it (or as found under a named folder).
    axis, time : str
        From the log metadata, else the file name and modification time.
    M, B, pole, dc_gain, coulomb_pos, coulomb_neg : float
        The identified model (units in :attr:`units`).
    fit_percent : float
        Simulation fit of the model on the log [%].
    method : str
        ``sidbe`` or ``joint``.
    effects : str
        Effects the diagnosis named, ``;``-separated ("" without ``--diagnose`` or when none).
    gap_before, gap_after : float
        Velocity gap [%] of the base and of the diagnosed model (``--diagnose`` only).
    error : str
        "" when the log went through, else the one-line reason.
    model : str
        Structure of the diagnosed model, ``base`` or ``base + <effects>`` ("" without ``--diagnose``).
    diagnosed_M, diagnosed_B, diagnosed_coulomb_pos, diagnosed_coulomb_neg : float
        Base parameters of the diagnosed model, refitted with its effects (``--diagnose`` only).
    units : mapping
        Unit of every parameter (``servobench.units.SignalUnits.parameters``); not a column.
    """

    log: str
    axis: str = ""
    time: str = ""
    M: float = NAN
    B: float = NAN
    pole: float = NAN
    dc_gain: float = NAN
    coulomb_pos: float = NAN
    coulomb_neg: float = NAN
    fit_percent: float = NAN
    method: str = ""
    effects: str = ""
    gap_before: float = NAN
    gap_after: float = NAN
    error: str = ""
    units: Mapping[str, str] = field(default_factory=dict, compare=False)
    # added columns, keyword-only: rows built by position keep their meaning
    model: str = field(default="", kw_only=True)
    diagnosed_M: float = field(default=NAN, kw_only=True)
    diagnosed_B: float = field(default=NAN, kw_only=True)
    diagnosed_coulomb_pos: float = field(default=NAN, kw_only=True)
    diagnosed_coulomb_neg: float = field(default=NAN, kw_only=True)

    @property
    def ok(self) -> bool:
        """True when the log went through (no error)."""
        return not self.error

    @property
    def diagnosed(self) -> bool:
        """True when the diagnosis ran and refitted the base (its ``diagnosed_*`` are numbers)."""
        return bool(self.model) and math.isfinite(self.diagnosed_M)

    def compared(self, parameter: str) -> float:
        """``parameter`` of the model the trend compares: the diagnosed one where the diagnosis
        ran, else identify's; ``pole`` (-B/M) and ``dc_gain`` (1/B) follow their M and B."""
        if not self.diagnosed:
            return float(getattr(self, parameter))
        if parameter == "pole":
            return -self.diagnosed_B / self.diagnosed_M
        if parameter == "dc_gain":
            return 1.0 / self.diagnosed_B if self.diagnosed_B else NAN
        return float(getattr(self, f"diagnosed_{parameter}"))

    @property
    def effect_names(self) -> tuple[str, ...]:
        return tuple(e for e in self.effects.split(EFFECT_SEPARATOR) if e)

    def record(self) -> dict[str, Any]:
        """The row as ``{column: value}``, NaN as None (comparable, JSON- and Parquet-ready)."""
        return {c: _none_if_nan(getattr(self, c)) for c in COLUMNS}


assert tuple(f.name for f in fields(FleetRow) if f.name != "units") == COLUMNS


def _none_if_nan(value: Any) -> Any:
    return None if isinstance(value, float) and math.isnan(value) else value


def _csv_text(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value)  # shortest text that reads back to the same float
    return str(value)


def write_csv(rows: Sequence[FleetRow], path: str | Path) -> Path:
    """Write ``fleet.csv`` (header, then one row per log, in the order given)."""
    path = Path(path)
    with open(path, "w", encoding="utf-8", newline="") as fh:
        out = csv.writer(fh, lineterminator="\n")
        out.writerow(COLUMNS)
        for row in rows:
            out.writerow(_csv_text(v) for v in row.record().values())
    return path


def units_by_axis(rows: Sequence[FleetRow]) -> dict[str, dict[str, str]]:
    """The parameter units of each axis, from its first row that has them."""
    units: dict[str, dict[str, str]] = {}
    for row in rows:
        if row.units and row.axis not in units:
            units[row.axis] = dict(row.units)
    return units


def write_parquet(rows: Sequence[FleetRow], path: str | Path) -> Path:
    """Write ``fleet.parquet``: strings and float64 (null where not found), units in the schema."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    schema = pa.schema(
        [pa.field(c, pa.float64() if c in NUMBERS else pa.string()) for c in COLUMNS],
        metadata={UNITS_KEY: json.dumps(units_by_axis(rows), sort_keys=True).encode()},
    )
    records = [row.record() for row in rows]
    table = pa.Table.from_pylist(records, schema=schema)
    pq.write_table(table, Path(path))
    return Path(path)
