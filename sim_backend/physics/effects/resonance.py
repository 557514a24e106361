"""``resonance`` -- a compliant transmission: a series mode between motor and load.

Model: the motor (inertia ``(1 - ratio) M``, friction, command) drives the
load (inertia ``ratio M``) through a spring and damper; the viscous term
splits with the inertia and the sensor sits on the load. Without friction
the load velocity is the rigid-body response times the series mode
``(2 zeta wn s + wn^2) / (s^2 + (2 zeta wn + B/M) s + wn^2)``, ``wn`` [rad/s],
``zeta`` [1]. The linear part is propagated exactly;
sub-steps of at most ``1/wn`` resolve friction and reversals.
"""

from __future__ import annotations

import math

import numpy as np

from servobench.errors import UsageError
from servobench.sim_backend.physics.effects.spec import (
    Coupling,
    EffectSpec,
    ParamSpec,
    Screening,
    ScreenInput,
    Terms,
)

EFFECT = EffectSpec(
    name="resonance",
    summary="series mode of a compliant transmission",
    params=(
        ParamSpec(
            "wn",
            "res_wn",
            "rad/s",
            "natural frequency of the series mode",
            0.0,
            open_lower=True,
            default=None,
        ),
        ParamSpec(
            "zeta", "res_zeta", "1", "damping ratio of the series mode", 0.0, 5.0, default=0.1
        ),
        ParamSpec(
            "ratio",
            "res_ratio",
            "1",
            "share of the inertia on the load side",
            0.02,
            0.98,
            default=0.5,
        ),
    ),
    signature="a narrow peak in the residual spectrum: the ratio of measured to simulated "
    "velocity spectra rises to a resonance above the rigid-body bandwidth",
    fit="peak of the empirical ratio |V_measured / V_simulated| gives wn, its height zeta; then "
    "simulation error on wn and zeta with the base",
)

#: Smallest peak of |V_measured / V_simulated| taken for a mode.
MIN_PEAK_RATIO = 1.3
#: Smallest coherence of measured and simulated velocity where a peak is looked for.
MIN_COHERENCE = 0.5


def contribute(p, plant, terms: Terms) -> None:
    if terms.coupling is not None:
        raise UsageError("resonance cannot be combined with another coupling (backlash)")
    wn, zeta, r = float(p["wn"]), float(p["zeta"]), float(p["ratio"])
    mr = r * (1 - r) * plant.M
    terms.coupling = Coupling(
        "spring", r, stiffness=wn * wn * mr, damping=2 * zeta * wn * mr, measured="load"
    )
    terms.substep_s = min(terms.substep_s, 1.0 / wn)


def screen(ctx: ScreenInput) -> Screening:
    from servobench.bench.dsp.spectral import csd, welch  # the diagnosis's, not scipy.signal's

    fs = 1.0 / ctx.dt_s
    num = den = out = res = 0.0
    freqs = None
    for r in ctx.runs:
        nper = int(min(r.v.size, 2 ** int(np.log2(max(r.v.size // 4, 16)))))
        freqs, pxy = csd(r.v_sim, r.v, fs, nper)
        _, pxx = welch(r.v_sim, fs, nper)
        _, pyy = welch(r.v, fs, nper)
        _, prr = welch(r.residual, fs, nper)
        num, den, out, res = num + pxy, den + pxx, out + pyy, res + prr
    base = ctx.base
    f_rigid = base["B"] / base["M"] / (2 * math.pi)
    ratio = np.abs(num) / np.maximum(den, 1e-300)
    # Where the simulated velocity has little power, sensor noise alone makes the ratio
    # large: only coherent frequencies count.
    coherence = np.abs(num) ** 2 / np.maximum(den * out, 1e-300)
    band = (
        (freqs > max(2 * f_rigid, 3 * freqs[1])) & (freqs < 0.45 * fs) & (coherence > MIN_COHERENCE)
    )
    if not np.any(band):
        guess = {"wn": 2 * math.pi * 0.2 * fs, "zeta": 0.1}
        bounds = {"wn": (2 * math.pi * freqs[1], math.pi * fs), "zeta": (0.005, 1.0)}
        return Screening(0.0, guess, bounds, "no coherent band above the rigid-body bandwidth")
    idx = np.flatnonzero(band)
    i = int(idx[np.argmax(ratio[idx])])
    peak, f0 = float(ratio[i]), float(freqs[i])
    near = (freqs > 0.6 * f0) & (freqs < 1.6 * f0)
    share = float(res[near].sum() / max(res.sum(), 1e-300))
    score = share * (1 - 1 / peak) if peak >= MIN_PEAK_RATIO else 0.0
    zeta = float(np.clip(1.0 / (2 * peak), 0.01, 0.7))
    wn = 2 * math.pi * f0
    evidence = (
        f"the measured/simulated spectrum ratio has a peak (x{peak:.2g}) and "
        f"{100 * share:.0f}% of the residual power lies around it: a series mode"
    )
    bounds = {"wn": (0.5 * wn, 2.0 * wn), "zeta": (0.005, 1.0)}
    return Screening(score, {"wn": wn, "zeta": zeta}, bounds, evidence, scan=("wn",))
