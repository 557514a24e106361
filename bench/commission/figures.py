"""The commissioning figures, rendered to PNG bytes (matplotlib, Agg).

Each function takes result objects and arrays and returns PNG bytes; none
touches a drive or a file. The report embeds them as base64 images.

Signals: ``t`` [s], ``u`` [command units], ``v`` [velocity units/s]; the
model is ``1/(M s + B)`` with Coulomb friction ``coulomb_pos`` (positive
motion) and ``coulomb_neg`` (negative motion), both magnitudes.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence

import numpy as np

from bench.commission.closedloop import FRICTION_FLOOR, CompensationCheck
from bench.logio import ExperimentLog, RunData

#: Figure size [inch] and resolution [dpi] of every plot.
FIGSIZE = (8.0, 4.2)
DPI = 90
#: Velocity bins of the friction map.
FRICTION_BINS = 40


def _figure(rows: int = 1, height: float = FIGSIZE[1]):
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(FIGSIZE[0], height), dpi=DPI)
    axes = fig.subplots(rows, 1, sharex=True, squeeze=False)[:, 0]
    return fig, axes


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def excitation(log: ExperimentLog) -> bytes:
    """Command of every run against time."""
    fig, (ax,) = _figure()
    for run in log.runs:
        ax.step(run.t, run.u, where="post", lw=0.8, label=f"run {run.run}")
    ax.set(xlabel="t [s]", ylabel="u [command units]", title="Excitation")
    ax.legend(loc="upper right")
    return _png(fig)


def model_velocity(run: RunData, M: float, B: float, fc_pos: float, fc_neg: float, fs_hz: float) -> np.ndarray:
    """Velocity the identified model predicts for ``run.u`` from the run's first state [velocity units/s]."""
    from sim_backend.plant import PlantParams, PlantState, simulate_coulomb

    params = PlantParams(M=M, B=B, fc_pos=max(fc_pos, FRICTION_FLOOR), fc_neg=max(fc_neg, FRICTION_FLOOR))
    v0 = float(run.v[0]) if run.v is not None else 0.0
    v, _, _ = simulate_coulomb(run.u, 1.0 / fs_hz, params, PlantState(v0, 0.0))
    return v


def velocities(log: ExperimentLog, M: float, B: float, fc_pos: float, fc_neg: float) -> bytes:
    """Measured velocity and the model's simulation, one panel per run."""
    runs = [r for r in log.runs if r.v is not None]
    fig, axes = _figure(max(len(runs), 1), height=2.4 * max(len(runs), 1) + 0.6)
    for ax, run in zip(axes, runs, strict=False):
        sim = model_velocity(run, M, B, fc_pos, fc_neg, log.fs_hz)
        ax.plot(run.t, run.v, lw=0.8, label="measured")
        ax.plot(run.t, sim, lw=0.8, ls="--", label="model")
        ax.set(ylabel="v [units/s]", title=f"Velocity, run {run.run}")
        ax.legend(loc="upper right")
    axes[-1].set_xlabel("t [s]")
    return _png(fig)


def _differential(log: ExperimentLog) -> tuple[np.ndarray, np.ndarray]:
    runs = [r for r in log.runs if r.v is not None]
    if len(runs) >= 2:
        n = min(len(runs[0]), len(runs[1]))
        return runs[0].u[:n] - runs[1].u[:n], runs[0].v[:n] - runs[1].v[:n]
    return runs[0].u, runs[0].v


def bode(log: ExperimentLog, M: float, B: float) -> bytes:
    """Measured FRF of the differential pair ``u1-u2 -> v1-v2`` (H1 estimate) and the fitted model.

    The model is drawn as sampled: ``(1-a)/(B (z-a))`` with ``a = exp(-B T/M)``,
    the one-cycle lag of feedback sampled before the command acts included.
    """
    from scipy import signal

    u, v = _differential(log)
    fs = log.fs_hz
    nperseg = int(min(len(u), max(256, 2 ** math.floor(math.log2(max(len(u) // 4, 2))))))
    f, puu = signal.welch(u - u.mean(), fs, nperseg=nperseg)
    _, puv = signal.csd(u - u.mean(), v - v.mean(), fs, nperseg=nperseg)
    _, coh = signal.coherence(u, v, fs, nperseg=nperseg)
    keep = (f > 0) & (puu > 1e-12 * puu.max()) & (coh > 0.5)
    T = 1.0 / fs
    fm = np.logspace(math.log10(max(f[1], 1e-3)), math.log10(0.5 * fs * 0.999), 300)
    z = np.exp(2j * math.pi * fm * T)
    a = math.exp(-B * T / M)
    model = (1 - a) / (B * (z - a))
    fig, (ax_m, ax_p) = _figure(2, height=5.2)
    h = puv[keep] / puu[keep]
    ax_m.loglog(f[keep], np.abs(h), ".", ms=3, label="measured (u1-u2 -> v1-v2)")
    ax_m.loglog(fm, np.abs(model), label=f"model 1/({M:.4g} s + {B:.4g})")
    ax_m.set(ylabel="|V/U|", title="Frequency response")
    ax_m.legend(loc="lower left")
    ax_p.semilogx(f[keep], np.degrees(np.angle(h)), ".", ms=3)
    ax_p.semilogx(fm, np.degrees(np.angle(model)))
    ax_p.set(xlabel="f [Hz]", ylabel="phase [deg]")
    return _png(fig)


def friction_map(log: ExperimentLog, M: float, B: float, fc_pos: float, fc_neg: float) -> bytes:
    """Dissipative force ``u - M dv/dt`` against velocity, binned, with the model ``B v + F_f(v)``.

    The force is taken from the exact ZOH step of the linear block,
    ``u_k - B (v_{k+1} - a v_k)/(1 - a)``, on intervals where the velocity keeps its sign.
    """
    T = 1.0 / log.fs_hz
    a = math.exp(-B * T / M)
    vs, fs = [], []
    for run in log.runs:
        if run.v is None or len(run) < 2:
            continue
        v0, v1, u = run.v[:-1], run.v[1:], run.u[:-1]
        same = (np.sign(v0) == np.sign(v1)) & (v0 != 0)
        force = u - B * (v1 - a * v0) / (1 - a) + B * v0  # = u - (M dv/dt) in ZOH terms
        vs.append(v0[same])
        fs.append(force[same])
    fig, (ax,) = _figure()
    if vs and np.concatenate(vs).size:
        v = np.concatenate(vs)
        force = np.concatenate(fs)
        edges = np.linspace(v.min(), v.max(), FRICTION_BINS + 1)
        idx = np.clip(np.digitize(v, edges) - 1, 0, FRICTION_BINS - 1)
        centers = 0.5 * (edges[1:] + edges[:-1])
        counts = np.bincount(idx, minlength=FRICTION_BINS)
        sums = np.bincount(idx, weights=force, minlength=FRICTION_BINS)
        ok = counts > 0
        ax.plot(v, force, ",", alpha=0.3, color="0.6")
        ax.plot(centers[ok], sums[ok] / counts[ok], "o", ms=4, label="measured (binned)")
        grid = np.linspace(v.min(), v.max(), 400)
        ax.plot(grid, B * grid + np.where(grid > 0, fc_pos, np.where(grid < 0, -fc_neg, 0.0)),
                label=f"model B v + Fc (Fc+ {fc_pos:.3g}, Fc- {fc_neg:.3g})")  # fmt: skip
        ax.legend(loc="upper left")
    ax.axhline(0, color="0.8", lw=0.5)
    ax.axvline(0, color="0.8", lw=0.5)
    ax.set(xlabel="v [units/s]", ylabel="u - M dv/dt [command units]", title="Friction-velocity map")
    return _png(fig)


def bump(t: np.ndarray, u: np.ndarray, v: np.ndarray) -> bytes:
    """The bump test: command and velocity against time."""
    fig, (ax_u, ax_v) = _figure(2, height=4.6)
    ax_u.step(t, u, where="post", lw=0.8)
    ax_u.set(ylabel="u [command units]", title="Bump test")
    ax_v.plot(t, v, lw=0.8)
    ax_v.set(xlabel="t [s]", ylabel="v [units/s]")
    return _png(fig)


def compensation(check: CompensationCheck) -> bytes:
    """Tracking of the slow reversing reference with PI alone and with friction feed-forward."""
    fig, (ax_v, ax_e) = _figure(2, height=5.2)
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
    return _png(fig)


def gaps(labels: Sequence[str], before: Sequence[float], after: Sequence[float], unit: str) -> bytes:
    """Bar chart of a model-measurement gap before and after the diagnosis."""
    fig, (ax,) = _figure()
    x = np.arange(len(labels))
    ax.bar(x - 0.2, before, 0.4, label="before")
    ax.bar(x + 0.2, after, 0.4, label="after")
    ax.set_xticks(x, list(labels))
    ax.set(ylabel=unit, title="Diagnosis: gap between simulation and measurement")
    ax.legend()
    return _png(fig)
