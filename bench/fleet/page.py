"""``trend.html``: the fleet's trends on one self-contained page, plots embedded as PNG.

Sections: a summary of every axis (flagged ones first, with their
reasons), an overview plot of the watched drifts of all axes against time,
one section per axis (its parameters against time with the first record's
value dashed and the threshold band on the watched ones, the drift of its
latest record, and its records with the units of each parameter), and the
logs that failed with their reasons. The page is built
with :mod:`servobench.bench.report.html` and the one figure helper
:mod:`servobench.bench.report.figure`. :func:`axis_figure` is a pure
function of a trend, so ``servobench fleet`` draws the axes' figures on the
Dask workers and hands them to :func:`write_page`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING

from servobench.bench.fleet.table import FleetRow
from servobench.bench.fleet.trend import PARAMETERS, WATCHED, AxisTrend
from servobench.bench.report.figure import new_figure, png_bytes
from servobench.bench.report.html import (
    FAIL,
    PASS,
    REMARK,
    Figure,
    Grid,
    KeyValues,
    Section,
    Verdict,
    render,
)

if TYPE_CHECKING:
    from matplotlib.figure import Figure

TREND_FILE = "trend.html"
#: Resolution of the embedded plots [dots per inch] (small: a fleet has hundreds of axes).
DPI = 72
_LABELS = {
    "M": "M", "B": "B", "pole": "pole", "dc_gain": "DC gain",
    "coulomb_pos": "Coulomb +", "coulomb_neg": "Coulomb -",
}  # fmt: skip


def _label(parameter: str, trend: AxisTrend) -> str:
    unit = trend.units.get(parameter, "")
    return f"{_LABELS[parameter]} [{unit}]" if unit else _LABELS[parameter]


#: Units of the time axis, ``(name, seconds)``, and the longest span each is used for [s].
TIME_UNITS = (("s", 1.0, 120.0), ("min", 60.0, 2 * 3600.0), ("h", 3600.0, 2 * 86400.0),
              ("days", 86400.0, math.inf))  # fmt: skip


def time_unit(span_s: float) -> tuple[str, float]:
    """The natural unit of a time span: ``("s", 1)`` up to 2 min, ``("min", 60)`` up to 2 h,
    ``("h", 3600)`` up to 2 days, else ``("days", 86400)``."""
    return next((name, seconds) for name, seconds, longest in TIME_UNITS if span_s <= longest)


def _elapsed(times: Sequence[datetime], origin: datetime) -> tuple[list[float], str]:
    """``times`` since ``origin`` in the natural unit of their span, and that unit's name."""
    span = max((t - origin).total_seconds() for t in times) if times else 0.0
    name, seconds = time_unit(span)
    return [(t - origin).total_seconds() / seconds for t in times], name


def _fixed_layout(fig: Figure, top: float) -> None:
    """Fixed margins instead of the helper's constrained layout (5x faster for many small panels)."""
    fig.set_layout_engine("none")
    fig.subplotpars.update(left=0.08, right=0.98, bottom=0.14, top=top, wspace=0.35, hspace=0.45)


def axis_figure(trend: AxisTrend, threshold_percent: float) -> bytes:
    """Six panels, one per parameter against days since the first record, as PNG bytes."""
    fig = new_figure(height_in=4.8)
    _fixed_layout(fig, top=0.88)
    axes = fig.subplots(2, 3, sharex=True)
    elapsed, unit = _elapsed(trend.times, trend.times[0])
    for ax, p in zip(axes.ravel(), PARAMETERS, strict=True):
        values = trend.values(p)
        ax.plot(elapsed, values, "o-", color="#a00" if trend.flagged else "#036")
        ax.axhline(values[0], ls="--", lw=0.8, color="#555")
        band = abs(values[0]) * threshold_percent / 100.0
        if p in WATCHED:
            ax.axhspan(values[0] - band, values[0] + band, color="#ddd", alpha=0.5, lw=0)
        # at least the threshold band in view: noise must not look like drift
        low, high = min(*values, values[0] - 1.2 * band), max(*values, values[0] + 1.2 * band)
        if high > low:
            ax.set_ylim(low - 0.05 * (high - low), high + 0.05 * (high - low))
        ax.ticklabel_format(axis="y", useOffset=False)
        ax.set_title(_label(p, trend), fontsize=9)
        ax.tick_params(labelsize=7)
    for ax in axes[1]:
        ax.set_xlabel(f"{unit} since {_when(trend.times[0], unit)}", fontsize=8)
    fig.suptitle(f"{trend.axis}: parameters against time (dashed: first record)", fontsize=10)
    return png_bytes(fig, dpi=DPI)


def overview_figure(trends: Sequence[AxisTrend], threshold_percent: float) -> bytes:
    """Drift [%] of the watched parameters of every axis against time, as PNG bytes."""
    fig = new_figure(height_in=3.0)
    _fixed_layout(fig, top=0.82)
    axes = fig.subplots(1, len(WATCHED), sharey=True)
    origin = min(t.times[0] for t in trends)
    _, unit = _elapsed([time for t in trends for time in t.times], origin)
    seconds = next(s for name, s, _ in TIME_UNITS if name == unit)
    for ax, p in zip(axes, WATCHED, strict=True):
        for t in trends:
            color, width = ("#a00", 1.5) if t.flagged else ("#9ab", 0.8)
            elapsed = [(time - origin).total_seconds() / seconds for time in t.times]
            ax.plot(elapsed, t.drift_series(p), ".-", color=color, lw=width)
        for sign in (1, -1):
            ax.axhline(sign * threshold_percent, ls="--", lw=0.8, color="#555")
        ax.set_title(f"{_LABELS[p]} drift [%]", fontsize=9)
        ax.tick_params(labelsize=7)
        ax.set_xlabel(f"{unit} since {_when(origin, unit)}", fontsize=8)
    fig.suptitle("Drift against each axis's first record (red: flagged)", fontsize=10)
    return png_bytes(fig, dpi=DPI)


def _when(origin: datetime, unit: str) -> str:
    """The origin of a time axis: its date for days, its date and time for shorter spans."""
    return origin.date().isoformat() if unit == "days" else origin.isoformat(sep=" ", timespec="seconds")


def _drift_cell(trend: AxisTrend, parameter: str) -> str:
    d = trend.drift.get(parameter)
    return "n/a" if d is None else f"{d:+.1f} %"


def _summary(ordered: Sequence[AxisTrend]) -> Grid:
    """One line per axis, flagged ones first: its status, watched drifts and reasons."""
    header = ["axis", "records", "status", *(f"{_LABELS[p]} drift" for p in WATCHED), "reasons"]
    rows = [
        [t.axis, len(t.records), "FLAGGED" if t.flagged else "ok",
         *(_drift_cell(t, p) for p in WATCHED), "; ".join(t.reasons)]
        for t in ordered
    ]  # fmt: skip
    classes = [["", "", FAIL if t.flagged else PASS] for t in ordered]
    return Grid("Every axis, latest record against its first", header, rows, classes)


def _records(trend: AxisTrend) -> Grid:
    """The records of an axis, oldest first, each parameter with its unit in the header."""
    header = ["time", *(_label(p, trend) for p in PARAMETERS), "fit [%]", "model", "log"]
    rows = [
        [r.time, *(r.compared(p) for p in PARAMETERS), float(r.fit_percent),
         r.model or "identified (no --diagnose)", r.log]
        for r in trend.records
    ]  # fmt: skip
    return Grid("Records", header, rows)


def _axis_section(trend: AxisTrend, threshold_percent: float, png: bytes | None) -> Section:
    verdict = "FLAGGED: " + "; ".join(trend.reasons) if trend.flagged else "not flagged"
    drift = KeyValues(
        "Drift of the latest record against the first",
        [(_label(p, trend), _drift_cell(trend, p)) for p in PARAMETERS],
    )
    figure = Figure(
        f"{trend.axis}: every parameter against the time since its first record (dashed: the "
        f"first record; grey band: ±{threshold_percent:g} % on the watched parameters).",
        png if png is not None else axis_figure(trend, threshold_percent),
    )
    blocks = [f"{len(trend.records)} records; {verdict}.", *(f"{s}." for s in trend.structure),
              drift, figure, _records(trend)]  # fmt: skip
    return Section(f"Axis {trend.axis}", blocks, level=3)


def render_page(
    rows: Sequence[FleetRow],
    trends: Sequence[AxisTrend],
    threshold_percent: float,
    figures: Sequence[bytes] | None = None,
) -> str:
    """The whole page as text; ``figures`` are the :func:`axis_figure` of ``trends``, in
    order, when drawn already (on the cluster), else they are drawn here."""
    drawn = dict(zip((t.axis for t in trends), figures, strict=True)) if figures else {}
    failed = [r for r in rows if not r.ok]
    ordered = sorted(trends, key=lambda t: (not t.flagged, t.axis))
    flagged = [t.axis for t in ordered if t.flagged]
    axes = Section("Axes", [_summary(ordered)] if ordered else ["No log went through."])
    if trends:
        axes.blocks.append(Figure(
            "Drift of the watched parameters of every axis against each axis's first record "
            f"[%]; red: flagged axes; dashed: ±{threshold_percent:g} %.",
            overview_figure(trends, threshold_percent),
        ))  # fmt: skip
    sections = [axes, *(_axis_section(t, threshold_percent, drawn.get(t.axis)) for t in ordered)]
    if failed:
        table = Grid("", ["log", "error"], [[r.log, r.error] for r in failed])
        sections.append(Section("Logs that failed", [table]))
    identity = KeyValues("", [
        ("logs", len(rows)),
        ("failed", len(failed)),
        ("axes", len(trends)),
        ("flagged", ", ".join(flagged) or "none"),
        ("threshold", f"±{threshold_percent:g} % on {', '.join(WATCHED)}"),
    ])  # fmt: skip
    return render("servobench fleet: friction trends", _verdict(rows, failed, flagged), identity,
                  sections)  # fmt: skip


def _verdict(rows: Sequence[FleetRow], failed: Sequence[FleetRow], flagged: list[str]) -> Verdict:
    if not rows or len(failed) == len(rows):
        return Verdict(FAIL, f"No trend: {len(failed)} of {len(rows)} logs failed.")
    n = len(flagged)
    words = ["No axis flagged" if n == 0 else f"{n} {'axis' if n == 1 else 'axes'} flagged"]
    if failed:
        words.append(f"{len(failed)} of {len(rows)} logs failed")
    status = FAIL if flagged else (REMARK if failed else PASS)
    return Verdict(status, "; ".join(words) + ".")


def write_page(
    rows: Sequence[FleetRow],
    trends: Sequence[AxisTrend],
    threshold_percent: float,
    out_dir: Path,
    figures: Sequence[bytes] | None = None,
) -> Path:
    """Write ``out_dir/trend.html`` (see :func:`render_page`); return its path."""
    path = Path(out_dir) / TREND_FILE
    path.write_text(render_page(rows, trends, threshold_percent, figures), encoding="utf-8")
    return path
