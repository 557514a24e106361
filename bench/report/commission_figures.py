"""The figures only commissioning draws, rendered to PNG bytes (matplotlib, Agg).

One excitation period (command and velocity of both runs; in closed loop
also the position in its travel window), the bump test
and the compensation check. The identification plots (FRF, velocities,
friction map) come from :mod:`servobench.bench.report.plots` through the
SIDBE procedure, the before/after plots from the diagnosis; the report
embeds all of them as base64 images.

Signals: ``t`` [s], ``u`` [u unit], ``v`` [v unit], the units a
:class:`~servobench.units.SignalUnits` names on every axis.
"""

from __future__ import annotations

import numpy as np

from servobench.bench.commission.closedloop import CompensationCheck
from servobench.bench.log.io import ExperimentLog
from servobench.bench.report.figure import new_figure, png_bytes
from servobench.units import SignalUnits

#: Height of a one-row figure [inch] and resolution [dpi] of the embedded plots.
HEIGHT_IN = 4.2
DPI = 100


def _figure(rows: int = 1, height_in: float = HEIGHT_IN):
    fig = new_figure(height_in)
    axes = fig.subplots(rows, 1, sharex=True, squeeze=False)[:, 0]
    return fig, axes


def period_window(log: ExperimentLog) -> tuple[int, int, int, int]:
    """``(start, stop, period index from 1, periods)`` of the last whole excitation period.

    The period length is the log's ``samples_per_period``; without it the
    whole shortest run is the window.
    """
    shortest = min(len(r) for r in log.runs)
    try:
        n = int(float(log.metadata.get("samples_per_period", "")))
    except ValueError:
        n = 0
    if not 0 < n <= shortest:
        return 0, shortest, 1, 1
    whole = shortest // n
    return (whole - 1) * n, whole * n, whole, whole


def excitation_period(
    log: ExperimentLog, units: SignalUnits, window: tuple[float, float] | None = None
) -> bytes:
    """Command and velocity of every run over the last whole excitation period.

    A closed-loop log (its runs carry ``u_exc``) shows the binary excitation and,
    thinner, the total command the hold loop made of it, and a third panel of
    the position against the held one and the travel ``window`` ``(xmin, xmax)``.
    """
    start, stop, index, periods = period_window(log)
    closed = all(r.u_exc is not None and r.x is not None for r in log.runs)
    fig, axes = _figure(3 if closed else 2, 6.6 if closed else 5.0)
    ax_u, ax_v = axes[0], axes[1]
    for i, run in enumerate(log.runs):
        t = run.t[start:stop]
        if closed:
            ax_u.step(t, run.u_exc[start:stop], where="post", lw=1.0, color=f"C{i}",
                      label=f"run {run.run}: excitation u{run.run}")  # fmt: skip
            ax_u.step(t, run.u[start:stop], where="post", lw=0.6, alpha=0.6, color=f"C{i}", ls="--",
                      label=f"run {run.run}: total, hold included")  # fmt: skip
            axes[2].plot(t, run.x[start:stop], lw=0.9, color=f"C{i}", label=f"run {run.run}: x{run.run}")
        else:
            ax_u.step(t, run.u[start:stop], where="post", lw=1.0, color=f"C{i}", label=f"run {run.run}: u{run.run}")
        if run.v is not None:
            ax_v.plot(t, run.v[start:stop], lw=0.9, color=f"C{i}", label=f"run {run.run}: v{run.run}")
    length_s = log.runs[0].t[stop - 1] - log.runs[0].t[start] + (log.runs[0].t[1] - log.runs[0].t[0])
    ax_u.set(ylabel=units.label("u"),
             title=f"Excitation period {index} of {periods} ({length_s:.3g} s), steady state")  # fmt: skip
    ax_v.set(ylabel=units.label("v"))
    if closed:
        _travel_panel(axes[2], log, units, window)
    axes[-1].set(xlabel="t [s]")
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    return png_bytes(fig, DPI)


def _travel_panel(ax, log: ExperimentLog, units: SignalUnits, window: tuple[float, float] | None) -> None:
    """The held position and the travel window on the position panel."""
    x_ref = log.runs[0].x_ref
    if x_ref is not None:
        ax.axhline(float(x_ref[0]), color="k", lw=0.8, ls=":", label="held position x_ref")
    if window is not None and all(np.isfinite(window)):
        for edge in window:
            ax.axhline(edge, color="C3", lw=1.0, label="travel limit" if edge == window[0] else None)
    ax.set(ylabel=units.label("x"))


def bump(t: np.ndarray, u: np.ndarray, v: np.ndarray, units: SignalUnits) -> bytes:
    """The bump test: command and velocity against time."""
    fig, (ax_u, ax_v) = _figure(2, 4.6)
    ax_u.step(t, u, where="post", lw=0.8)
    ax_u.set(ylabel=units.label("u"), title="Bump test: pulses each way, smallest first")
    ax_v.plot(t, v, lw=0.8)
    ax_v.set(xlabel="t [s]", ylabel=units.label("v"))
    for ax in (ax_u, ax_v):
        ax.grid(True, alpha=0.3)
    return png_bytes(fig, DPI)


def compensation(check: CompensationCheck, units: SignalUnits) -> bytes:
    """Tracking of the slow reversing reference with PI alone and with friction feed-forward."""
    fig, (ax_v, ax_e) = _figure(2, 5.2)
    a, b = check.without_ff, check.with_ff
    v = units.of("v")
    ax_v.plot(a.t_s, a.v_ref, "k", lw=0.8, label="reference")
    ax_v.plot(a.t_s, a.v, lw=0.8, label="PI")
    ax_v.plot(b.t_s, b.v, lw=0.8, ls="--", label="PI + friction feed-forward")
    ax_v.set(ylabel=units.label("v"), title="Velocity loop on the identified plant (simulation)")
    ax_v.legend(loc="upper right", fontsize=8)
    ax_e.plot(a.t_s, a.v_ref - a.v, lw=0.8, label=f"PI (rms {a.rms_error:.3g} {v})")
    ax_e.plot(b.t_s, b.v_ref - b.v, lw=0.8, label=f"PI + FF (rms {b.rms_error:.3g} {v})")
    ax_e.set(xlabel="t [s]", ylabel=f"tracking error [{v}]")
    ax_e.legend(loc="upper right", fontsize=8)
    for ax in (ax_v, ax_e):
        ax.grid(True, alpha=0.3)
    return png_bytes(fig, DPI)
