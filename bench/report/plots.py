"""PNG plots of an identification result (matplotlib, object API, no pyplot state).

* ``frf.png``: the measured differential FRF at the excited lines with the
  fitted model's sampled response (SIDBE logs only);
* ``time.png``: measured and simulated velocity of each run;
* ``friction.png``: friction force ``u - M dv/dt - B v`` against velocity,
  with the identified Coulomb levels.

The functions read result objects only.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from servobench.bench.model import IdentificationResult
from servobench.bench.report.figure import new_figure, save_png

#: Most points drawn per scatter/line (the rest are thinned out evenly).
MAX_POINTS = 20_000


def _thin(*arrays: np.ndarray) -> list[np.ndarray]:
    n = len(arrays[0])
    step = max(1, int(math.ceil(n / MAX_POINTS)))
    return [a[::step] for a in arrays]


def plot_frf(result: IdentificationResult, path: str | Path) -> Path | None:
    """Bode plot of the measured FRF and the model; None when the result has no FRF."""
    frf = result.frf
    if frf is None:
        return None
    f = frf.f_hz
    grid = np.geomspace(f.min() / 2, min(f.max() * 2, 0.499 / frf.dt_s), 400)
    g_model = result.model.frequency_response(grid, frf.dt_s)
    fig = new_figure(2 * 3.2)
    ax_m, ax_p = fig.subplots(2, 1, sharex=True)
    ax_m.loglog(f, np.abs(frf.G), "o", label="measured (V1-V2)/(U1-U2)")
    ax_m.loglog(grid, np.abs(g_model), "-", label=f"model ({result.method})")
    ax_m.set_ylabel("|G| [v per u]")
    ax_m.legend(loc="lower left")
    ax_m.grid(True, which="both", alpha=0.3)
    ax_p.semilogx(f, np.degrees(np.angle(frf.G)), "o")
    ax_p.semilogx(grid, np.degrees(np.angle(g_model)), "-")
    ax_p.set_ylabel("phase [deg]")
    ax_p.set_xlabel("frequency [Hz]")
    ax_p.grid(True, which="both", alpha=0.3)
    fig.suptitle(
        f"Differential FRF, pole {result.model.pole:.4g} 1/s, DC gain {result.model.dc_gain:.4g}"
    )
    save_png(fig, path)
    return Path(path)


def plot_time(result: IdentificationResult, path: str | Path) -> Path | None:
    """Measured vs simulated velocity, one panel per run; None without a verification."""
    ver = result.verification
    if ver is None:
        return None
    fig = new_figure(len(ver.runs) * 2.6)
    axes = np.atleast_1d(fig.subplots(len(ver.runs), 1, squeeze=False)[:, 0])
    for ax, run in zip(axes, ver.runs, strict=True):
        t, v, vs = _thin(run.t, run.v, run.v_sim)
        ax.plot(t, v, lw=0.8, label="measured")
        ax.plot(t, vs, lw=0.8, ls="--", label="simulated")
        ax.set_ylabel("v [units/s]")
        ax.set_title(f"run {run.run}: fit {run.fit_percent:.2f} %", fontsize=9)
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc="upper right")
    axes[-1].set_xlabel("t [s]")
    fig.suptitle(f"Verification by simulation: fit {result.fit_percent:.2f} %")
    save_png(fig, path)
    return Path(path)


def friction_samples(result: IdentificationResult) -> tuple[np.ndarray, np.ndarray]:
    """Velocity [units/s] and friction force ``u - M dv/dt - B v`` [command units] at each usable sample."""
    ver = result.verification
    m = result.model
    vs, fs = [], []
    for run in ver.runs:
        v, u, t = run.v, run.u, run.t
        dt = np.diff(t)
        a = np.exp(-m.B * dt / m.M)
        b = (1.0 - a) / m.B
        same = (np.sign(v[:-1]) == np.sign(v[1:])) & (v[:-1] != 0)
        force = u[:-1] - (v[1:] - a * v[:-1]) / b
        vs.append(v[:-1][same])
        fs.append(force[same])
    return np.concatenate(vs), np.concatenate(fs)


def plot_friction(result: IdentificationResult, path: str | Path) -> Path | None:
    """Friction map: force against velocity with the identified Coulomb levels."""
    if result.verification is None:
        return None
    v, f = friction_samples(result)
    if v.size == 0:
        return None
    v, f = _thin(v, f)
    m = result.model
    fig = new_figure(3.6)
    ax = fig.subplots()
    ax.plot(v, f, ".", ms=1.5, alpha=0.5, zorder=3, label="u - M dv/dt - B v")
    vmax = float(np.max(np.abs(v)))
    ax.hlines(
        [m.coulomb_pos],
        0,
        vmax,
        colors="C1",
        lw=1.2,
        ls="--",
        label=f"+{m.coulomb_pos:.4g} (v > 0)",
    )
    ax.hlines(
        [-m.coulomb_neg],
        -vmax,
        0,
        colors="C2",
        lw=1.2,
        ls="--",
        label=f"-{m.coulomb_neg:.4g} (v < 0)",
    )
    spread = max(m.coulomb_pos, m.coulomb_neg, 1e-9)
    lo, hi = np.percentile(f, [1, 99])
    ax.set_ylim(min(lo, -2 * spread), max(hi, 2 * spread))
    ax.set_xlabel("v [units/s]")
    ax.set_ylabel("friction force [command units]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title("Friction map")
    save_png(fig, path)
    return Path(path)


def write_plots(result: IdentificationResult, out_dir: str | Path) -> list[Path]:
    """Write ``frf.png`` (when available), ``time.png`` and ``friction.png`` to ``out_dir``."""
    out = Path(out_dir)
    written = [
        plot_frf(result, out / "frf.png"),
        plot_time(result, out / "time.png"),
        plot_friction(result, out / "friction.png"),
    ]
    return [p for p in written if p is not None]
