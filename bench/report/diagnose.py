"""Outputs of a diagnosis: the JSON object, ``comparison.csv`` and a Markdown report with plots.

Everything here consumes a :class:`~servobench.bench.diagnose.workflow.Diagnosis`; nothing is recomputed
except the residual analysis of the final model, for the before/after plots.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from servobench.bench.diagnose.signatures import compute_signatures
from servobench.bench.diagnose.workflow import Diagnosis
from servobench.bench.report.figure import new_figure, save_png


def _clean(value):
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, (np.floating, float)):
        f = float(value)
        return f if math.isfinite(f) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def to_json(d: Diagnosis) -> dict:
    """The one JSON object ``servobench diagnose --json`` prints."""
    base_before = d.steps[0].fit.candidate.base
    out = {
        "effects": [
            {"name": e.name, "parameters": dict(e.parameters), "evidence": e.evidence}
            for e in d.effects
        ],
        "gap_before": d.gap_before,
        "gap_after": d.gap_after,
        "base_before": dict(base_before),
        "base_after": d.base,
        "steps": [
            {
                "added": list(s.added),
                "model": list(s.fit.candidate.names),
                "gap": s.fit.gap,
                "gap_held_out": s.fit.gap_held_out,
            }
            for s in d.steps
        ],
        "comparison": d.data.comparison,
        "velocity": "derived from position" if d.data.derived else "measured",
        "noise_floor": d.trace.noise_floor,
        "findings": d.signatures.findings(),
        "tried": [
            [{"effects": list(names), "gap_held_out": gap} for names, gap in rnd]
            for rnd in d.trace.rounds
        ],
    }
    return _clean(out)


def write_comparison_csv(d: Diagnosis, path: str | Path) -> Path:
    """``run,t,v_measured,v_before,v_after`` for every sample of every run."""
    path = Path(path)
    before, after = d.steps[0].fit.v_sim, d.steps[-1].fit.v_sim
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["run", "t", "v_measured", "v_before", "v_after"])
        for r, vb, va in zip(d.data.segments, before, after, strict=True):
            for row in zip(np.full(len(r.t), r.run), r.t, r.v, vb, va, strict=True):
                w.writerow([int(row[0])] + [format(float(x), ".10g") for x in row[1:]])
    return path


def _plots(d: Diagnosis, out: Path) -> list[tuple[str, str]]:
    data = d.data
    before, after = d.steps[0].fit.v_sim, d.steps[-1].fit.v_sim
    sig_b = d.signatures
    sig_a = compute_signatures(data, after)
    figs: list[tuple[str, str]] = []

    fig = new_figure(3.6, 10)
    axes = fig.subplots(1, 2)
    for ax, attr, label in (
        (axes[0], "vs_velocity", "velocity"),
        (axes[1], "vs_position", "position"),
    ):
        for sig, name, style in ((sig_b, "base model", "o-"), (sig_a, "final model", "s-")):
            b = getattr(sig, attr)
            ax.plot(b.centres, b.means, style, ms=3, label=f"{name} (eta2 {b.eta2:.2f})")
        ax.axhline(0, color="0.5", lw=0.8)
        ax.set_xlabel(f"{label} [units{'/s' if label == 'velocity' else ''}]")
        ax.set_ylabel("mean residual [units/s]")
        ax.legend(fontsize=8)
    fig.suptitle("Residual (measured - simulated velocity) against velocity and position")
    figs.append(_save(fig, out / "residual_vs_state.png"))

    fig = new_figure(3.6, 7)
    ax = fig.subplots()
    ax.semilogy(sig_b.spectrum_hz[1:], sig_b.spectrum[1:], label="base model")
    ax.semilogy(sig_a.spectrum_hz[1:], sig_a.spectrum[1:], label="final model")
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("residual PSD [(units/s)^2/Hz]")
    ax.legend()
    ax.set_title("Residual spectrum")
    figs.append(_save(fig, out / "residual_spectrum.png"))

    n = len(data.segments)
    fig = new_figure(2.8 * n, 10)
    axes = fig.subplots(n, 1, squeeze=False)
    for ax, r, vb, va in zip(axes[:, 0], data.segments, before, after, strict=True):
        ax.plot(r.t, r.v, color="0.2", lw=0.8, label="measured")
        ax.plot(r.t, vb, lw=0.8, label=f"base model ({d.gap_before:.2f}%)")
        ax.plot(r.t, va, lw=0.8, ls="--", label=f"final model ({d.gap_after:.2f}%)")
        ax.set_ylabel(f"run {r.run} v [units/s]")
        ax.legend(fontsize=8, loc="upper right")
    axes[-1, 0].set_xlabel("t [s]")
    fig.suptitle("Measured velocity against the simulated models")
    figs.append(_save(fig, out / "overlay.png"))

    fig = new_figure(3.6, 7)
    ax = fig.subplots()
    labels = ["base"] + ["+" + "+".join(s.added) for s in d.steps[1:]]
    gaps = [s.fit.gap for s in d.steps]
    held = [s.fit.gap_held_out for s in d.steps]
    xs = np.arange(len(labels))
    ax.bar(xs - 0.2, gaps, 0.4, label="all samples")
    ax.bar(xs + 0.2, held, 0.4, label="held-out samples")
    if d.trace.noise_floor > 0:
        ax.axhline(d.trace.noise_floor, color="0.4", ls=":", label="sensor-noise floor")
    ax.set_xticks(xs, labels, rotation=15)
    ax.set_ylabel("velocity gap [% NRMSE]")
    ax.legend()
    ax.set_title("Gap at each step")
    figs.append(_save(fig, out / "gap_steps.png"))
    return figs


def _save(fig, path: Path) -> tuple[str, str]:
    save_png(fig, path, dpi=110)
    return path.name, path.stem.replace("_", " ")


def write_report(d: Diagnosis, out_dir: str | Path) -> Path:
    """Write ``comparison.csv``, the plots and ``report.md`` into ``out_dir``; return the report."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_comparison_csv(d, out / "comparison.csv")
    figs = _plots(d, out)
    lines = [
        "# servobench diagnose",
        "",
        f"Log: `{Path(d.data.source).name or 'log'}`; velocity {('derived from position' if d.data.derived else 'measured')}; "
        f"comparison: {d.data.comparison}.",
        "",
        f"**Velocity gap (NRMSE): {d.gap_before:.3g}% before, {d.gap_after:.3g}% after.**",
        "",
        "## Effects added",
        "",
    ]
    if not d.effects:
        lines.append("None: no library effect pays on held-out data; the base model stands.")
    for i, e in enumerate(d.effects, 1):
        params = ", ".join(f"{k} = {v:.4g}" for k, v in e.parameters.items())
        lines.append(f"{i}. **{e.name}** ({params}): {e.evidence}.")
    lines += ["", "## Steps", "", "| model | gap [%] | held-out gap [%] |", "| --- | --- | --- |"]
    for s in d.steps:
        name = (
            "base" if not s.fit.candidate.names else "base + " + " + ".join(s.fit.candidate.names)
        )
        lines.append(f"| {name} | {s.fit.gap:.3g} | {s.fit.gap_held_out:.3g} |")
    base = d.steps[0].fit.candidate.base
    lines += [
        "",
        f"Base model: M = {base['M']:.4g}, B = {base['B']:.4g}, coulomb_pos = {base['coulomb_pos']:.4g}, "
        f"coulomb_neg = {base['coulomb_neg']:.4g}; sensor-noise floor {d.trace.noise_floor:.3g}%.",
        "",
        "## Where the base model disagrees",
        "",
    ]
    lines += [f"- {s}" for s in d.signatures.findings()]
    lines += ["", "## Candidates refitted", ""]
    for i, rnd in enumerate(d.trace.rounds, 1):
        tried = ", ".join(f"{'+'.join(n)} {g:.3g}%" for n, g in rnd)
        lines.append(f"- round {i} (held-out gap): {tried}")
    lines.append("")
    for name, title in figs:
        lines += [f"![{title}]({name})", ""]
    path = out / "report.md"
    path.write_text("\n".join(lines), encoding="utf-8")
    return path
