"""Human-readable summaries of identification results (rich, on stdout)."""

from __future__ import annotations

import json
import math
import sys
from typing import Any

from servobench.bench.model import IdentificationResult


def print_json(obj: dict[str, Any]) -> None:
    """Exactly one JSON object on stdout."""
    sys.stdout.write(json.dumps(obj, allow_nan=False) + "\n")
    sys.stdout.flush()


def _pm(value: float, std: float | None) -> str:
    if std is None or not math.isfinite(std):
        return f"{value:.6g}"
    return f"{value:.6g} ± {std:.2g}"


def rate_text(fs_hz: float, achieved_hz: float, link_max_hz: float = math.inf) -> str:
    """``"100 Hz set, 99.98 Hz achieved (the link carries 147 Hz)"`` for a summary row."""
    text = f"{fs_hz:g} Hz set"
    if math.isfinite(achieved_hz):
        text += f", {achieved_hz:.5g} Hz achieved"
    if math.isfinite(link_max_hz):
        text += f" (the link carries {link_max_hz:.0f} Hz)"
    return text


def print_result(
    result: IdentificationResult,
    title: str = "Identified model",
    extra: dict[str, str] | None = None,
) -> None:
    """A table of the model with 1-sigma uncertainties, the fit and the selection sentence."""
    from rich.console import Console
    from rich.table import Table

    m, s = result.model, result.std
    table = Table(title=title, show_header=True, header_style="bold")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    table.add_row("M", _pm(m.M, s.get("M")))
    table.add_row("B", _pm(m.B, s.get("B")))
    table.add_row("pole -B/M [1/s]", f"{m.pole:.6g}")
    table.add_row("DC gain 1/B", f"{m.dc_gain:.6g}")
    table.add_row("Coulomb + (v > 0)", _pm(m.coulomb_pos, s.get("coulomb_pos")))
    table.add_row("Coulomb - (v < 0)", _pm(m.coulomb_neg, s.get("coulomb_neg")))
    if m.resonance is not None:
        table.add_row("resonance [Hz]", f"{m.resonance.f_hz:.4g} (zeta {m.resonance.zeta:.3g})")
    table.add_row("fit (simulation)", f"{result.fit_percent:.2f} %")
    table.add_row("method", f"{result.method} ({result.estimator})")
    for key, value in (extra or {}).items():
        table.add_row(key, value)
    console = Console()
    console.print(table)
    console.print(result.selection)
    for note in result.notes:
        console.print(f"note: {note}")
