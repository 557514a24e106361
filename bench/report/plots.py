"""PNG plots of an identification result (matplotlib, object API, no pyplot state).

* ``frf.png``: the measured differential FRF at the excited lines with its
  uncertainty (2 standard errors, from the spread over the periods), the
  identified linear block, and the model with its friction put through the
  same differential FRF, which shows and explains the friction bias at low
  amplitude (SIDBE logs only);
* ``time.png``: measured and simulated velocity of each run;
* ``friction.png``: the friction force ``u - M dv/dt - B v`` binned by
  velocity (mean and spread, zero-phase filtered) with the identified
  Coulomb levels.

Axis labels carry the units of the result (``result.units``, from the log's
``unit_*`` metadata); :func:`captions` gives each figure a sentence for a
report. The functions read result objects only; the numbers behind the
friction map and the FRF bands come from :mod:`servobench.bench.report.plot_data`.
"""

from __future__ import annotations

import math
import textwrap
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from servobench.bench.model.servo import IdentificationResult
from servobench.bench.report.figure import new_figure, save_png
from servobench.bench.report.plot_data import FrfEvidence, FrictionMap, frf_evidence, friction_map

if TYPE_CHECKING:
    from matplotlib.figure import Figure

#: Most points drawn per line (the rest are thinned out evenly).
MAX_POINTS = 20_000
#: Error bars of the FRF: this many standard errors (about 95 %).
FRF_SIGMAS = 2.0
#: Coulomb friction over the excitation amplitude from which an FRF that cannot
#: show the model's friction bias warns of one.
FRICTION_SHARE_NOTE = 0.05

FRF_FILE, TIME_FILE, FRICTION_FILE = "frf.png", "time.png", "friction.png"


def _thin(*arrays: np.ndarray) -> list[np.ndarray]:
    n = len(arrays[0])
    step = max(1, int(math.ceil(n / MAX_POINTS)))
    return [a[::step] for a in arrays]


def _frf_label(result: IdentificationResult) -> str:
    """Unit of the FRF magnitude: velocity per command, as the DC gain."""
    return f"|G| [{result.units.parameters()['dc_gain']}]"


def _bias_note(result: IdentificationResult, ev: FrfEvidence) -> str:
    """The sentence that explains a friction-biased differential FRF, empty when there is no bias."""
    m, u = result.model, result.units.of("u")
    if not math.isfinite(ev.amplitude):
        return ""
    share = 100.0 * max(m.coulomb_pos, m.coulomb_neg) / ev.amplitude
    friction = (f"at ±{ev.amplitude:.3g} {u} the Coulomb friction (+{m.coulomb_pos:.3g} / "
                f"-{m.coulomb_neg:.3g} {u}) is {share:.0f} % of the excitation")  # fmt: skip
    if ev.with_friction is None:
        if share < 100 * FRICTION_SHARE_NOTE:
            return ""
        return (f"Possible friction bias: {friction}, and the differential pair cancels friction only "
                "where both runs stick and slip together. This FRF was measured on position, so the "
                "spread over periods and the model's own friction bias are not drawn.")  # fmt: skip
    if not ev.biased:
        return ""
    bias = ev.friction_bias
    worst = int(np.argmax(bias))
    return (
        f"Friction bias: {friction}. The two runs stick and slip at different instants, so friction "
        "does not cancel in (V1-V2)/(U1-U2) and the measured points leave the linear block. The "
        "identified model simulated with its friction and put through the same differential FRF "
        f"(open circles) predicts the offset: up to {100 * bias[worst]:.0f} % at {ev.f_hz[worst]:.3g} Hz."
    )


def _draw_frf(fig, result: IdentificationResult, ev: FrfEvidence) -> None:
    frf = result.frf
    f = ev.f_hz
    grid = np.geomspace(f.min() / 2, min(f.max() * 2, 0.499 / frf.dt_s), 300)
    g_model = result.model.frequency_response(grid, frf.dt_s)
    note = _bias_note(result, ev)
    rows = fig.add_gridspec(3 if note else 2, 1, height_ratios=[3, 2.4, 0.75][: 3 if note else 2])
    ax_m = fig.add_subplot(rows[0])
    ax_p = fig.add_subplot(rows[1], sharex=ax_m)
    mag = np.abs(ev.measured)
    if ev.std_error is not None:
        err = FRF_SIGMAS * ev.std_error
        lower = np.minimum(err, 0.95 * mag)  # a bar may not cross zero on a log axis
        ax_m.errorbar(f, mag, yerr=[lower, err], fmt="o", ms=5, capsize=3, zorder=3,
                      label=f"measured (V1-V2)/(U1-U2), ±{FRF_SIGMAS:g} std. error over periods")  # fmt: skip
        phase_err = np.degrees(np.minimum(err / mag, math.pi))
        ax_p.errorbar(f, np.degrees(np.angle(ev.measured)), yerr=phase_err, fmt="o", ms=5,
                      capsize=3, zorder=3)  # fmt: skip
    else:
        ax_m.loglog(f, mag, "o", ms=5, zorder=3, label="measured (V1-V2)/(U1-U2)")
        ax_p.semilogx(f, np.degrees(np.angle(ev.measured)), "o", ms=5, zorder=3)
    ax_m.plot(grid, np.abs(g_model), "-", color="C1", label=f"identified linear block ({result.method})")
    ax_p.plot(grid, np.degrees(np.angle(g_model)), "-", color="C1")
    if ev.with_friction is not None:
        style = dict(ls="none", marker="o", ms=9, mfc="none", mec="C2", mew=1.2, zorder=4)
        ax_m.plot(f, np.abs(ev.with_friction), **style,
                  label="model with its friction, same differential FRF (simulated)")  # fmt: skip
        ax_p.plot(f, np.degrees(np.angle(ev.with_friction)), **style)
    ax_m.set(xscale="log", yscale="log", ylabel=_frf_label(result))
    ax_m.tick_params(labelbottom=False)
    ax_p.set(xscale="log", ylabel="phase [deg]", xlabel="frequency [Hz]")
    ax_m.legend(loc="lower left", fontsize=8)
    for ax in (ax_m, ax_p):
        ax.grid(True, which="major", alpha=0.35)
        ax.grid(True, which="minor", alpha=0.12)
    if note:
        ax_n = fig.add_subplot(rows[2])
        ax_n.axis("off")
        ax_n.text(0.0, 0.5, textwrap.fill(note, 125), transform=ax_n.transAxes, ha="left", va="center",
                  fontsize=8, bbox=dict(boxstyle="round", fc="#fff8e0", ec="#c9a227"))  # fmt: skip
    m = result.model
    at = f" at ±{ev.amplitude:.3g} {result.units.of('u')}" if math.isfinite(ev.amplitude) else ""
    fig.suptitle(
        f"Differential FRF{at}: pole {m.pole:.4g} 1/s, "
        f"DC gain {m.dc_gain:.4g} {result.units.parameters()['dc_gain']}"
    )


def frf_figure(result: IdentificationResult) -> Figure | None:
    """Bode plot of the measured FRF, its uncertainty and the model; None when the result has no FRF."""
    ev = frf_evidence(result)
    if ev is None:
        return None
    fig = new_figure(7.0)
    _draw_frf(fig, result, ev)
    return fig


def time_figure(result: IdentificationResult) -> Figure | None:
    """Measured vs simulated velocity, one panel per run; None without a verification."""
    ver = result.verification
    if ver is None:
        return None
    fig = new_figure(len(ver.runs) * 2.6)
    axes = np.atleast_1d(fig.subplots(len(ver.runs), 1, squeeze=False, sharex=True)[:, 0])
    label = result.units.label("v")
    for ax, run in zip(axes, ver.runs, strict=True):
        t, v, vs = _thin(run.t, run.v, run.v_sim)
        ax.plot(t, v, lw=0.8, label="measured")
        ax.plot(t, vs, lw=0.8, ls="--", label="simulated from the logged command")
        ax.set_ylabel(label)
        ax.set_title(f"run {run.run}: fit {run.fit_percent:.2f} %", fontsize=9)
        ax.grid(True, alpha=0.3)
    fig.legend(*axes[0].get_legend_handles_labels(), loc="outside lower center", ncol=2, fontsize=8)
    axes[-1].set_xlabel("t [s]")
    fig.suptitle(f"Verification by simulation: fit {result.fit_percent:.2f} %")
    return fig


def _draw_friction(fig, result: IdentificationResult, fm: FrictionMap) -> None:
    ax = fig.subplots()
    units = result.units
    u = units.of("u")
    ax.plot(fm.v_cloud, fm.force_cloud, ".", ms=1.5, color="0.6", alpha=0.35, zorder=1,
            label="samples")  # fmt: skip
    ax.errorbar(fm.v_centre, fm.force_mean, yerr=fm.force_std, fmt="o", ms=4, capsize=2.5,
                color="C0", zorder=3, label="mean per velocity bin, ±1 std (spread)")  # fmt: skip
    vmax = float(np.max(np.abs(fm.v_centre))) if fm.v_centre.size else 1.0
    ax.hlines(fm.coulomb_pos, 0, vmax * 1.05, colors="C1", lw=2, zorder=4,
              label=f"identified Coulomb +{fm.coulomb_pos:.4g} {u} (v > 0)")  # fmt: skip
    ax.hlines(-fm.coulomb_neg, -vmax * 1.05, 0, colors="C2", lw=2, zorder=4,
              label=f"identified Coulomb -{fm.coulomb_neg:.4g} {u} (v < 0)")  # fmt: skip
    lo = min(np.min(fm.force_mean - fm.force_std), -fm.coulomb_neg) if fm.v_centre.size else -1.0
    hi = max(np.max(fm.force_mean + fm.force_std), fm.coulomb_pos) if fm.v_centre.size else 1.0
    pad = 0.35 * max(hi - lo, 1e-9)
    ax.set_ylim(lo - pad, hi + pad)
    ax.axhline(0, color="k", lw=0.6)
    ax.axvline(0, color="k", lw=0.6)
    ax.set_xlabel(units.label("v", "velocity (filtered)"))
    ax.set_ylabel(f"friction force u - M dv/dt - B v [{u}]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    outside = np.mean((fm.force_cloud < lo - pad) | (fm.force_cloud > hi + pad)) * 100
    beyond = f"; {outside:.0f} % of the samples lie beyond the view" if outside >= 1 else ""
    ax.set_title(f"Friction map (zero-phase low-pass {fm.cutoff_hz:.3g} Hz on v and u before d/dt{beyond})",
                 fontsize=9)  # fmt: skip


def friction_figure(result: IdentificationResult) -> Figure | None:
    """Friction map: binned friction force against velocity with the identified Coulomb levels."""
    fm = friction_map(result)
    if fm is None or fm.v_centre.size == 0:
        return None
    fig = new_figure(3.8)
    _draw_friction(fig, result, fm)
    return fig


def _save(fig: Figure | None, path: str | Path) -> Path | None:
    return None if fig is None else save_png(fig, path)


def plot_frf(result: IdentificationResult, path: str | Path) -> Path | None:
    """:func:`frf_figure` written to ``path``; None when the result has no FRF."""
    return _save(frf_figure(result), path)


def plot_time(result: IdentificationResult, path: str | Path) -> Path | None:
    """:func:`time_figure` written to ``path``; None without a verification."""
    return _save(time_figure(result), path)


def plot_friction(result: IdentificationResult, path: str | Path) -> Path | None:
    """:func:`friction_figure` written to ``path``; None without a verification."""
    return _save(friction_figure(result), path)


def captions(result: IdentificationResult) -> dict[str, str]:
    """A sentence per figure file name, for reports."""
    u, v = result.units.of("u"), result.units.of("v")
    return {
        FRF_FILE: (
            "Frequency response of the differential pair (V1-V2)/(U1-U2) at the excited lines, with "
            f"{FRF_SIGMAS:g} standard errors from the spread over the excitation periods, against the "
            "identified linear block 1/(M s + B). Open circles: the identified model with its "
            "Coulomb friction, simulated on the logged commands and put through the same "
            "differential FRF; where they follow the measured points, friction explains the offset."
        ),
        TIME_FILE: (
            f"Measured velocity [{v}] of each run against the velocity the identified model "
            "simulates from the logged command (verification by simulation)."
        ),
        FRICTION_FILE: (
            f"Friction force [{u}] against velocity [{v}]: u - M dv/dt - B v with the identified M and B, "
            "velocity and command through the same zero-phase low-pass before differentiating, "
            "binned by velocity (mean and spread); the lines are the identified Coulomb levels."
        ),
    }


def write_plots(result: IdentificationResult, out_dir: str | Path) -> list[Path]:
    """Write ``frf.png`` (when available), ``time.png`` and ``friction.png`` to ``out_dir``."""
    out = Path(out_dir)
    written = [
        plot_frf(result, out / FRF_FILE),
        plot_time(result, out / TIME_FILE),
        plot_friction(result, out / FRICTION_FILE),
    ]
    return [p for p in written if p is not None]
