"""The figures of the diagnose report, each with the caption the report prints under it.

Axes carry the log's units (``unit_u``/``unit_v``/``unit_x`` metadata, named
generically when the log states none); the residual spectrum has a
logarithmic frequency axis. Everything is drawn from a
:class:`~servobench.bench.diagnose.workflow.Diagnosis`; only the final model's
residual curves are recomputed (:func:`~servobench.bench.diagnose.signatures.compute_signatures`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from servobench.bench.diagnose.signatures import compute_signatures
from servobench.bench.diagnose.workflow import Diagnosis
from servobench.bench.report.figure import new_figure, save_png


@dataclass(frozen=True)
class Figure:
    """A written figure: file name (in the report's folder) and caption."""

    name: str
    caption: str


def _model_label(d: Diagnosis) -> str:
    names = d.final.names
    return "final model (base + " + " + ".join(names) + ")" if names else "final model (base)"


def residual_vs_state(d: Diagnosis, out: Path, sig_a) -> Figure:
    units = d.data.units
    fig = new_figure(3.6, 10)
    axes = fig.subplots(1, 2)
    for ax, attr, sig_unit, label in (
        (axes[0], "vs_velocity", "v", "velocity"),
        (axes[1], "vs_position", "x", "position"),
    ):
        for sig, name, style in (
            (d.signatures, "base model", "o-"),
            (sig_a, _model_label(d), "s-"),
        ):
            b = getattr(sig, attr)
            ax.plot(b.centres, b.means, style, ms=3, label=f"{name} (eta2 {b.eta2:.2f})")
        ax.axhline(0, color="0.5", lw=0.8)
        ax.set_xlabel(f"{label} [{units.of(sig_unit)}]")
        ax.set_ylabel(f"mean residual [{units.of('v')}]")
        ax.legend(fontsize=7)
    fig.suptitle("Residual (measured - simulated velocity) against velocity and position")
    name = "residual_vs_state.png"
    save_png(fig, out / name, dpi=110)
    return Figure(
        name,
        "Mean residual (measured minus simulated velocity) in bins of velocity (left) and "
        "position (right), for the base model and the final model; eta2 is the share of the "
        "residual variance the binned curve explains.",
    )


def residual_spectrum(d: Diagnosis, out: Path, sig_a) -> Figure:
    units = d.data.units
    fig = new_figure(3.6, 7)
    ax = fig.subplots()
    sb = d.signatures
    ax.loglog(sb.spectrum_hz[1:], sb.spectrum[1:], label="base model")
    ax.loglog(sig_a.spectrum_hz[1:], sig_a.spectrum[1:], label=_model_label(d))
    floor = d.verdict.floor.percent / 100.0 * float(np.std(d.data.cat("v")))
    if floor > 0:
        level = floor**2 / (0.5 * d.data.fs_hz)  # white noise of the floor's rms
        ax.axhline(level, color="0.4", ls=":", label="noise floor, as white noise")
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel(f"residual PSD [({units.of('v')})^2/Hz]")
    ax.legend(fontsize=8)
    ax.set_title("Residual spectrum")
    name = "residual_spectrum.png"
    save_png(fig, out / name, dpi=110)
    return Figure(
        name,
        "Power spectral density of the velocity residual (Welch) of the base and the final "
        "model, on logarithmic axes; the dotted line is the noise floor spread as white noise "
        "over the band.",
    )


def overlay(d: Diagnosis, out: Path) -> Figure:
    data, units = d.data, d.data.units
    before, after = d.steps[0].fit.v_sim, d.steps[-1].fit.v_sim
    n = len(data.segments)
    fig = new_figure(2.8 * n, 10)
    axes = fig.subplots(n, 1, squeeze=False)
    for ax, r, vb, va in zip(axes[:, 0], data.segments, before, after, strict=True):
        ax.plot(r.t, r.v, color="0.2", lw=0.8, label="measured")
        ax.plot(r.t, vb, lw=0.8, label=f"base model (gap {d.gap_before:.3g}%)")
        ax.plot(r.t, va, lw=0.8, ls="--", label=f"{_model_label(d)} (gap {d.gap_after:.3g}%)")
        ax.set_ylabel(f"run {r.run}: v [{units.of('v')}]")
        ax.legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("t [s]")
    fig.suptitle("Measured velocity against the simulated models")
    name = "overlay.png"
    save_png(fig, out / name, dpi=110)
    return Figure(
        name,
        f"Measured velocity of each run with the base model and the final model simulated on "
        f"the logged command ({data.comparison}).",
    )


def gap_steps(d: Diagnosis, out: Path) -> Figure:
    fig = new_figure(3.6, 7)
    ax = fig.subplots()
    labels = ["base"] + ["+" + "+".join(s.added) for s in d.steps[1:]]
    xs = np.arange(len(labels))
    ax.bar(xs - 0.2, [s.fit.gap for s in d.steps], 0.4, label="all samples")
    ax.bar(xs + 0.2, [s.fit.gap_held_out for s in d.steps], 0.4, label="held-out samples")
    ax.axhline(d.verdict.floor.percent, color="0.4", ls=":", label="noise floor")
    ax.set_xticks(xs, labels, rotation=15)
    ax.set_ylabel("velocity gap [% NRMSE]")
    ax.legend()
    ax.set_title("Gap at each step")
    name = "gap_steps.png"
    save_png(fig, out / name, dpi=110)
    return Figure(
        name,
        "Velocity gap (rms error over the measured velocity's standard deviation) of the base "
        "model and after each accepted addition, on all samples and on the held-out samples "
        "that decided it, against the noise floor.",
    )


def write_figures(d: Diagnosis, out: Path) -> list[Figure]:
    """Every figure of the report, written into ``out``."""
    sig_a = compute_signatures(d.data, d.steps[-1].fit.v_sim)
    return [
        residual_vs_state(d, out, sig_a),
        residual_spectrum(d, out, sig_a),
        overlay(d, out),
        gap_steps(d, out),
    ]
