"""Trend per axis: every parameter against time, its drift, and the flag of a failing axis.

The records of an axis are the rows of its logs that went through (a row
with an ``error`` is left out), ordered by time (then by log name). Drift is
taken against the axis's first record::

    drift [%] = 100 * (value - first) / |first|

for ``M``, ``B``, ``pole``, ``dc_gain``, ``coulomb_pos`` and ``coulomb_neg``.
An axis's :attr:`AxisTrend.drift` is that of its latest record -- where the
axis stands now -- and the axis is flagged when

- a Coulomb level (either direction) or ``B`` has drifted by more than the
  threshold (default 20 %) in either sense, or
- its latest record names an effect (``--diagnose``) that the first did not, or
- its units changed between records (the numbers are then not comparable).

Like is compared with like: each record's parameters are those of the model
``--diagnose`` refitted (:meth:`FleetRow.compared`: the base parameters of
the diagnosed model, so that an effect that appears -- a Stribeck peak --
does not read as a drift of B and of the Coulomb levels), and a change of
the model's structure between two records (``base`` -> ``base + stribeck``)
is said in :attr:`AxisTrend.structure` and among the reasons.

A first value of 0 gives no percentage (``None``); a watched parameter that
grows from 0 flags the axis. Each flag comes with one sentence in
:attr:`AxisTrend.reasons`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

from servobench.bench.fleet.table import FleetRow
from servobench.bench.log.identity import parse_time
from servobench.errors import UsageError

#: Parameters trended, in table order.
PARAMETERS = ("M", "B", "pole", "dc_gain", "coulomb_pos", "coulomb_neg")
#: Parameters whose drift flags an axis.
WATCHED = ("coulomb_pos", "coulomb_neg", "B")
#: Default drift threshold [%].
DEFAULT_THRESHOLD_PERCENT = 20.0


@dataclass(frozen=True)
class AxisTrend:
    """One axis over time.

    Attributes
    ----------
    axis : str
    records : tuple of FleetRow
        Its rows without error, oldest first.
    times : tuple of datetime
        Their times (aware).
    drift : mapping
        Drift [%] of each of :data:`PARAMETERS`, latest record against the first
        (``None`` where the first value is 0).
    flagged : bool
    reasons : tuple of str
        One sentence per cause of the flag.
    units : mapping
        Unit of each parameter (from the first record).
    structure : tuple of str
        One sentence per change of the diagnosed model's structure between two records.
    """

    axis: str
    records: tuple[FleetRow, ...]
    times: tuple[datetime, ...]
    drift: Mapping[str, float | None]
    flagged: bool
    reasons: tuple[str, ...]
    units: Mapping[str, str] = field(default_factory=dict)
    structure: tuple[str, ...] = ()

    def values(self, parameter: str) -> list[float]:
        """``parameter`` of every record, oldest first."""
        return [r.compared(parameter) for r in self.records]

    def drift_series(self, parameter: str) -> list[float]:
        """Drift [%] of ``parameter`` of every record against the first (NaN where undefined)."""
        values = self.values(parameter)
        return [
            _drift(values[0], v) if _drift(values[0], v) is not None else math.nan for v in values
        ]

    def to_json(self) -> dict[str, Any]:
        """``{"axis", "records", "drift", "flagged", "reasons", "units", "first", "last"}``."""
        return {
            "axis": self.axis,
            "records": len(self.records),
            "drift": {k: (None if v is None else round(v, 6)) for k, v in self.drift.items()},
            "flagged": self.flagged,
            "reasons": list(self.reasons),
            "units": dict(self.units),
            "first": self.records[0].time,
            "last": self.records[-1].time,
            "models": [r.model for r in self.records],
            "structure": list(self.structure),
        }


def _drift(first: float, value: float) -> float | None:
    if first == 0 or not (math.isfinite(first) and math.isfinite(value)):
        return None
    return 100.0 * (value - first) / abs(first)


def axis_trends(
    rows: Sequence[FleetRow], threshold_percent: float = DEFAULT_THRESHOLD_PERCENT
) -> tuple[AxisTrend, ...]:
    """The trend of every axis with at least one record, axes in name order.

    Raises
    ------
    UsageError
        ``threshold_percent`` is not a positive number.
    """
    if not (math.isfinite(threshold_percent) and threshold_percent > 0):
        raise UsageError(f"--threshold must be a percentage > 0, got {threshold_percent:g}")
    by_axis: dict[str, list[tuple[datetime, FleetRow]]] = {}
    for row in rows:
        if row.ok:
            by_axis.setdefault(row.axis, []).append((parse_time(row.time), row))
    trends = []
    for axis in sorted(by_axis):
        ordered = sorted(by_axis[axis], key=lambda item: (item[0], item[1].log))
        trends.append(_trend(axis, ordered, threshold_percent))
    return tuple(trends)


def _trend(axis: str, ordered: list[tuple[datetime, FleetRow]], threshold: float) -> AxisTrend:
    times = tuple(t for t, _ in ordered)
    records = tuple(r for _, r in ordered)
    first, last = records[0], records[-1]
    drift = {p: _drift(first.compared(p), last.compared(p)) for p in PARAMETERS}
    units = dict(first.units)
    reasons = _drift_reasons(first, last, drift, threshold, units)
    new = [e for e in last.effect_names if e not in first.effect_names]
    if new:
        reasons.append(f"effect {', '.join(new)} appeared on {last.time}, absent on {first.time}")
    structure = tuple(
        f"model structure changed on {b.time}: {a.model} -> {b.model}; the drift compares the base "
        "parameters of the diagnosed models"
        for a, b in zip(records, records[1:], strict=False)
        if a.model and b.model and a.model != b.model
    )
    changed = next((r for r in records if r.units and dict(r.units) != units), None)
    if changed is not None and units:
        reasons.append(
            f"units changed on {changed.time} ({_unit_text(units)} -> {_unit_text(changed.units)}): "
            "the records are not comparable"
        )
    return AxisTrend(axis, records, times, drift, bool(reasons), tuple(reasons), units, structure)


def _drift_reasons(
    first: FleetRow,
    last: FleetRow,
    drift: Mapping[str, float | None],
    threshold: float,
    units: Mapping[str, str],
) -> list[str]:
    reasons = []
    for p in WATCHED:
        a, b = first.compared(p), last.compared(p)
        unit = f" {units[p]}" if units.get(p) else ""
        d = drift[p]
        if d is None:
            if a == 0 and b != 0:
                reasons.append(f"{p} rose from 0 to {b:.4g}{unit} since {first.time}")
            continue
        if abs(d) > threshold:
            reasons.append(
                f"{p} {d:+.1f} % since {first.time} ({a:.4g} -> {b:.4g}{unit}), "
                f"beyond ±{threshold:g} %"
            )
    return reasons


def _unit_text(units: Mapping[str, str]) -> str:
    return ", ".join(f"{k} [{units[k]}]" for k in ("u", "v") if k in units) or "none"
