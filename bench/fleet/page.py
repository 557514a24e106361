"""``trend.html``: the fleet's trends on one self-contained page, plots embedded as PNG.

Sections: a summary of every axis (flagged ones first, with their
reasons), an overview plot of the watched drifts of all axes against time,
one section per axis (its parameters against time, the first record's
value dashed, the threshold band on the watched ones, and the drift of each
record), and the logs that failed with their reasons. The page is built
with :mod:`servobench.bench.report.html` and the one figure helper
:mod:`servobench.bench.report.figure`. :func:`axis_figure` is a pure
function of a trend, so ``servobench fleet`` draws the axes' figures on the
Dask workers and hands them to :func:`write_page`.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING

from servobench.bench.fleet.table import FleetRow
from servobench.bench.fleet.trend import PARAMETERS, WATCHED, AxisTrend
from servobench.bench.report.figure import new_figure, png_bytes
from servobench.bench.report.html import Section, render

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


def _days(times: Sequence[datetime], origin: datetime) -> list[float]:
    """``times`` as days since ``origin`` [d]."""
    return [(t - origin).total_seconds() / 86400.0 for t in times]


def _fixed_layout(fig: Figure, top: float) -> None:
    """Fixed margins instead of the helper's constrained layout (5x faster for many small panels)."""
    fig.set_layout_engine("none")
    fig.subplotpars.update(left=0.08, right=0.98, bottom=0.14, top=top, wspace=0.35, hspace=0.45)


def axis_figure(trend: AxisTrend, threshold_percent: float) -> bytes:
    """Six panels, one per parameter against days since the first record, as PNG bytes."""
    fig = new_figure(height_in=4.8)
    _fixed_layout(fig, top=0.88)
    axes = fig.subplots(2, 3, sharex=True)
    days = _days(trend.times, trend.times[0])
    for ax, p in zip(axes.ravel(), PARAMETERS, strict=True):
        values = trend.values(p)
        ax.plot(days, values, "o-", color="#a00" if trend.flagged else "#036")
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
        ax.set_xlabel(f"days since {trend.records[0].time[:10]}", fontsize=8)
    fig.suptitle(f"{trend.axis}: parameters against time (dashed: first record)", fontsize=10)
    return png_bytes(fig, dpi=DPI)


def overview_figure(trends: Sequence[AxisTrend], threshold_percent: float) -> bytes:
    """Drift [%] of the watched parameters of every axis against time, as PNG bytes."""
    fig = new_figure(height_in=3.0)
    _fixed_layout(fig, top=0.82)
    axes = fig.subplots(1, len(WATCHED), sharey=True)
    origin = min(t.times[0] for t in trends)
    for ax, p in zip(axes, WATCHED, strict=True):
        for t in trends:
            color, width = ("#a00", 1.5) if t.flagged else ("#9ab", 0.8)
            ax.plot(_days(t.times, origin), t.drift_series(p), ".-", color=color, lw=width)
        for sign in (1, -1):
            ax.axhline(sign * threshold_percent, ls="--", lw=0.8, color="#555")
        ax.set_title(f"{_LABELS[p]} drift [%]", fontsize=9)
        ax.tick_params(labelsize=7)
        ax.set_xlabel(f"days since {origin.date().isoformat()}", fontsize=8)
    fig.suptitle("Drift against each axis's first record (red: flagged)", fontsize=10)
    return png_bytes(fig, dpi=DPI)


def _drift_text(trend: AxisTrend) -> str:
    parts = []
    for p in WATCHED:
        d = trend.drift.get(p)
        parts.append(f"{p} {'n/a' if d is None else f'{d:+.1f} %'}")
    return ", ".join(parts)


def _axis_section(trend: AxisTrend, threshold_percent: float, png: bytes | None) -> Section:
    rows = [
        (f"{r.time}", ", ".join(f"{p}={getattr(r, p):.5g}" for p in PARAMETERS)
         + (f"; effects: {r.effects}" if r.effects else "") + f"; log {r.log}")
        for r in trend.records
    ]  # fmt: skip
    drift = [(p, "n/a" if d is None else f"{d:+.2f} %") for p, d in trend.drift.items()]
    verdict = "FLAGGED: " + "; ".join(trend.reasons) if trend.flagged else "not flagged"
    return Section(
        title=f"Axis {trend.axis}",
        paragraphs=[f"{len(trend.records)} records; {verdict}."],
        tables=[("Drift of the latest record against the first", drift), ("Records", rows)],
        figures=[
            (
                f"{trend.axis}: parameters against time",
                png if png is not None else axis_figure(trend, threshold_percent),
            )
        ],  # fmt: skip
    )


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
    summary = [
        (t.axis, ("FLAGGED: " + "; ".join(t.reasons)) if t.flagged else f"ok ({_drift_text(t)})")
        for t in ordered
    ]
    sections = [Section("Axes", tables=[("", summary)] if summary else [])]
    if trends:
        sections[0].figures.append(
            ("Drift of every axis against time", overview_figure(trends, threshold_percent))
        )
    sections.extend(_axis_section(t, threshold_percent, drawn.get(t.axis)) for t in ordered)
    if failed:
        sections.append(
            Section("Logs that failed", tables=[("", [(r.log, r.error) for r in failed])])
        )
    status = "complete" if not failed else f"{len(failed)} of {len(rows)} logs failed"
    meta = {
        "logs": str(len(rows)),
        "failed": str(len(failed)),
        "axes": str(len(trends)),
        "flagged": ", ".join(t.axis for t in ordered if t.flagged) or "none",
        "threshold": f"±{threshold_percent:g} % on coulomb_pos, coulomb_neg and B",
    }
    return render("servobench fleet: friction trends", status, sections, meta)


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
