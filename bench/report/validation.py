"""The figure of ``servobench validate --out DIR``: measured against predicted.

Consumes a :class:`~servobench.bench.model.validate.Validation` only. One panel per
run with the measured velocity and the model's simulated one; for closed-loop
logs a last panel with the filtered command and the inverse model's command.
"""

from __future__ import annotations

from pathlib import Path

from servobench.bench.model.validate import Validation
from servobench.bench.report.figure import new_figure, save_png
from servobench.units import SignalUnits

FIGURE_FILE = "validation.png"


def write_validation_figure(
    result: Validation, out_dir: str | Path, units: SignalUnits | None = None, title: str = ""
) -> Path:
    """Write ``validation.png`` into ``out_dir`` (created); return its path."""
    units = units or SignalUnits()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    panels = len(result.runs) + (1 if result.closed_loop else 0)
    fig = new_figure(2.6 * panels + 0.6)
    axes = fig.subplots(panels, 1, squeeze=False)[:, 0]
    for ax, r in zip(axes, result.runs, strict=False):
        ax.plot(r.t, r.v, color="0.2", lw=0.8, label="measured")
        ax.plot(r.t, r.v_sim, lw=0.8, ls="--", label="model, simulated on the logged command")
        ax.set_ylabel(units.label("v", f"run {r.run}: v"))
        ax.legend(fontsize=8, loc="upper right")
    if result.closed_loop:
        ax = axes[-1]
        for r in result.runs:
            ax.plot(r.t, r.u_f, color="0.2", lw=0.8, label="measured command (filtered)")
            ax.plot(r.t, r.u_hat, lw=0.8, ls="--", label="inverse model on the measured motion")
        ax.set_ylabel(units.label("u"))
        handles, labels = ax.get_legend_handles_labels()
        ax.legend(handles[:2], labels[:2], fontsize=8, loc="upper right")
    axes[-1].set_xlabel("t [s]")
    figures = [f"fit {result.fit_percent:.2f} %", f"gap {result.gap_percent:.2f} %"]
    if result.force_error_percent is not None:
        figures.append(f"force error {result.force_error_percent:.2f} %")
    heading = f"{Path(title).name}: measured against predicted" if title else "Measured against predicted"
    fig.suptitle(f"{heading}\n{', '.join(figures)}; {result.samples:,} samples", fontsize=10)
    path = save_png(fig, out / FIGURE_FILE)
    return path
