"""Human-readable summaries of identification results (rich, on stdout).

Every quantity is shown with its unit, from the result's ``units`` (the
log's ``unit_*`` metadata, :mod:`servobench.units`); a log that states no
units gets one plain line saying the values are in command units.
"""

from __future__ import annotations

import json
import math
import sys
from typing import Any

from servobench.bench.identify.timing import COVERAGE
from servobench.bench.model.servo import IdentificationResult
from servobench.units import SignalUnits

#: Said when a log states no units.
NO_UNITS = (
    "units: the log states none (no unit_u/unit_v/unit_x lines), so the values are in the "
    "drive's command units and velocity units"
)


def print_json(obj: dict[str, Any]) -> None:
    """Exactly one JSON object on stdout."""
    sys.stdout.write(json.dumps(obj, allow_nan=False) + "\n")
    sys.stdout.flush()


def plus_minus(value: float, std: float | None) -> str:
    """``value ± std`` (std to two significant digits), or the value alone when std is unknown."""
    if std is None or not math.isfinite(std):
        return f"{value:.6g}"
    return f"{value:.6g} ± {std:.2g}"


def rate_text(fs_hz: float, achieved_hz: float, link_max_hz: float = math.inf, pace: str = "real") -> str:
    """``"100 Hz set, 99.98 Hz achieved (the link carries 147 Hz)"`` for a summary row.

    Under ``pace="fast"`` (a lock-step simulated drive that advances one cycle per
    exchange) the axis's time is its own clock at ``fs_hz``; how fast the host
    streamed is said as a multiple of real time, never as a rate the axis ran at.
    """
    link = f"the link carries {link_max_hz:.0f} Hz" if math.isfinite(link_max_hz) else ""
    if pace == "fast":
        text = f"{fs_hz:g} Hz on the drive's clock (lock-step, pace=fast"
        if math.isfinite(achieved_hz) and fs_hz > 0:
            text += f": streamed {achieved_hz / fs_hz:.3g}x faster than real time"
        return text + (f"; {link})" if link else ")")
    text = f"{fs_hz:g} Hz set"
    if math.isfinite(achieved_hz):
        text += f", {achieved_hz:.5g} Hz achieved"
    if math.isfinite(link_max_hz):
        text += f" (the link carries {link_max_hz:.0f} Hz)"
    return text


def derived_std(result: IdentificationResult) -> dict[str, float]:
    """1-sigma of the pole ``-B/M`` [1/s] and the DC gain ``1/B``, first-order propagation (M, B uncorrelated)."""
    m = result.model
    sm, sb = result.std.get("M", math.nan), result.std.get("B", math.nan)
    return {"pole": math.hypot(sb / m.M, m.B * sm / m.M**2), "dc_gain": sb / m.B**2}


def model_rows(result: IdentificationResult) -> list[tuple[str, str, str]]:
    """``(quantity, value ± 1 sigma, unit)`` of the identified model, in the order a reader expects."""
    m, s = result.model, result.std
    unit = result.units.parameters()
    d = derived_std(result)
    rows = [
        ("M (inertia)", plus_minus(m.M, s.get("M")), unit["M"]),
        ("B (viscous friction)", plus_minus(m.B, s.get("B")), unit["B"]),
        ("Coulomb friction, v > 0", plus_minus(m.coulomb_pos, s.get("coulomb_pos")), unit["coulomb_pos"]),
        ("Coulomb friction, v < 0", plus_minus(m.coulomb_neg, s.get("coulomb_neg")), unit["coulomb_neg"]),
        ("pole -B/M", plus_minus(m.pole, d.get("pole")), unit["pole"]),
        ("DC gain 1/B", plus_minus(m.dc_gain, d.get("dc_gain")), unit["dc_gain"]),
        ("drive action delay", plus_minus(m.delay_s * 1e3, s.get("delay_s", math.nan) * 1e3), "ms"),
    ]
    if m.resonance is not None:
        rows.append(("resonance", f"{m.resonance.f_hz:.4g} (zeta {m.resonance.zeta:.3g})", "Hz"))
    return rows


def units_sentence(units: SignalUnits) -> str:
    """One line naming the signal units, or :data:`NO_UNITS`."""
    if not units.known:
        return NO_UNITS
    return f"units: u in {units.of('u')}, v in {units.of('v')}, x in {units.of('x')}"


def timing_warning(result: IdentificationResult) -> list[str]:
    """The lines a summary starts with when the run's timing takes the model outside its
    stated accuracy (:meth:`~servobench.bench.identify.timing.TimingFigure.warning_lines`)."""
    return [] if result.timing is None else list(result.timing.warning_lines())


def print_timing_warning(result: IdentificationResult) -> None:
    """:func:`timing_warning`, first on stdout, unstyled."""
    for line in timing_warning(result):
        sys.stdout.write(line + "\n")
    sys.stdout.flush()


def timing_row(result: IdentificationResult) -> dict[str, str]:
    """``{"timing": "clock_source host, jitter p50/p99/max ..., model error ..."}`` for a summary
    table, empty for a log without a timing figure."""
    t = result.timing
    if t is None:
        return {}
    c = t.cycle
    ms = [f"{c.get(k, math.nan) * 1e3:.3g}" for k in ("host_jitter_p50_s", "host_jitter_p99_s", "host_jitter_max_s")]
    drift = ""
    if math.isfinite(t.drive_drift_ppm):
        drift = f"drive clock {t.drive_drift_ppm:+.3g} +- {t.drive_drift_std_ppm:.2g} ppm against the host's; "
    return {
        "timing": f"clock_source {t.clock_source}; {drift}host jitter p50/p99/max {'/'.join(ms)} ms; "
        f"{int(c.get('missed_cycles', 0) or 0)} missed cycles; predicted model error "
        f"{t.model_error_max_pct:.2g} % (1 sigma), {t.model_error_bound_pct:.2g} % at {COVERAGE:g} sigma: "
        f"{'within' if t.within_accuracy else 'OUTSIDE'} the stated {t.accuracy_pct:g} %"
    }


def print_result(
    result: IdentificationResult,
    title: str = "Identified model",
    extra: dict[str, str] | None = None,
) -> None:
    """A table of the model with 1-sigma uncertainties and units, the fit and the selection sentence."""
    from rich.console import Console
    from rich.table import Table

    print_timing_warning(result)
    table = Table(title=title, show_header=True, header_style="bold")
    table.add_column("quantity")
    table.add_column("value ± 1 sigma", justify="right")
    table.add_column("unit")
    for name, value, unit in model_rows(result):
        table.add_row(name, value, unit)
    table.add_row("fit (simulation)", f"{result.fit_percent:.2f}", "%")
    table.add_row("method", f"{result.method} ({result.estimator})", "")
    for key, value in {**(extra or {}), **timing_row(result)}.items():
        table.add_row(key, value, "")
    console = Console()
    console.print(table)
    console.print(units_sentence(result.units))
    console.print(result.selection)
    for note in result.notes:
        console.print(f"note: {note}")
