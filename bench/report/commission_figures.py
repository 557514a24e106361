"""The figures only commissioning draws, rendered to PNG bytes (matplotlib, Agg).

The excitation, the bump test and the compensation check. The
identification plots (FRF, velocities, friction map) come from
:mod:`servobench.bench.report.plots` through the SIDBE procedure, the before/after plots from
the diagnosis; the report embeds all of them as base64 images.

Signals: ``t`` [s], ``u`` [command units], ``v`` [velocity units/s].
"""

from __future__ import annotations

import numpy as np

from servobench.bench.commission.closedloop import CompensationCheck
from servobench.bench.logio import ExperimentLog
from servobench.bench.report.figure import new_figure, png_bytes

#: Height of a one-row figure [inch] and resolution [dpi] of the embedded plots.
HEIGHT_IN = 4.2
DPI = 90


def _figure(rows: int = 1, height_in: float = HEIGHT_IN):
    fig = new_figure(height_in)
    axes = fig.subplots(rows, 1, sharex=True, squeeze=False)[:, 0]
    return fig, axes


def excitation(log: ExperimentLog) -> bytes:
    """Command of every run against time."""
    fig, (ax,) = _figure()
    for run in log.runs:
        ax.step(run.t, run.u, where="post", lw=0.8, label=f"run {run.run}")
    ax.set(xlabel="t [s]", ylabel="u [command units]", title="Excitation")
    ax.legend(loc="upper right")
    return png_bytes(fig, DPI)


def bump(t: np.ndarray, u: np.ndarray, v: np.ndarray) -> bytes:
    """The bump test: command and velocity against time."""
    fig, (ax_u, ax_v) = _figure(2, 4.6)
    ax_u.step(t, u, where="post", lw=0.8)
    ax_u.set(ylabel="u [command units]", title="Bump test")
    ax_v.plot(t, v, lw=0.8)
    ax_v.set(xlabel="t [s]", ylabel="v [units/s]")
    return png_bytes(fig, DPI)


def compensation(check: CompensationCheck) -> bytes:
    """Tracking of the slow reversing reference with PI alone and with friction feed-forward."""
    fig, (ax_v, ax_e) = _figure(2, 5.2)
    a, b = check.without_ff, check.with_ff
    ax_v.plot(a.t_s, a.v_ref, "k", lw=0.8, label="reference")
    ax_v.plot(a.t_s, a.v, lw=0.8, label="PI")
    ax_v.plot(b.t_s, b.v, lw=0.8, ls="--", label="PI + friction feed-forward")
    ax_v.set(ylabel="v [units/s]", title="Velocity loop on the identified plant (simulation)")
    ax_v.legend(loc="upper right")
    ax_e.plot(a.t_s, a.v_ref - a.v, lw=0.8, label=f"PI (rms {a.rms_error:.3g})")
    ax_e.plot(b.t_s, b.v_ref - b.v, lw=0.8, label=f"PI + FF (rms {b.rms_error:.3g})")
    ax_e.set(xlabel="t [s]", ylabel="error [units/s]")
    ax_e.legend(loc="upper right")
    return png_bytes(fig, DPI)
