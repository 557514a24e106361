"""SIDBE as published: differential FRF, parametric fit, then Coulomb friction.

1. Average the steady-state periods of run 1 (``u1``) and run 2
   (``u2 = ratio * u1``) and take the differential FRF
   ``(V1 - V2)/(U1 - U2)`` at the excited lines (:mod:`servobench.bench.identify.frequency`).
2. Fit the linear block ``1/(M s + B)`` -- optionally with the series
   resonance of the paper's eq. (2)-(3) -- to that FRF.
3. With ``M`` and ``B`` fixed, estimate the Coulomb level of each direction
   by least squares of the friction force ``u - M dv/dt - B v`` over the
   intervals of each sign, in both runs, using the exact sampled form
   ``u[k] - (v[k+1] - a v[k]) / b``.

The differential pair does not cancel friction exactly (the zero-crossing
times of the two runs differ), so at amplitudes close to the friction level
the estimate is biased; :mod:`servobench.bench.identify.joint` is not.

Closed-loop logs (a hold loop kept the axis inside its travel): ``u`` is the
total command the drive applied, the hold loop's share included, and the FRF
is taken from it. The loop feeds noise back into ``u``, but the lines carry
the excitation, identical in every period and (scaled) in both runs, so the
averaged spectra at the lines converge to the noise-free response.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from servobench.bench.identify.dataset import Dataset
from servobench.bench.identify.derivative import filter_command, settle_samples
from servobench.bench.identify.estimate import MethodEstimate
from servobench.bench.identify.frequency import (
    detrend_position,
    differential_frf,
    fit_linear_block,
    position_over_velocity,
)
from servobench.bench.identify.regression import noise_std_from_residual, select_pairs
from servobench.bench.model.servo import Resonance, ServoModel
from servobench.errors import IdentificationError

#: Pairs closer to zero velocity than this many noise sigmas are not used for friction.
NOISE_SIGMAS = 3.0
#: Most sample pairs in the friction regression (evenly thinned beyond).
MAX_PAIRS = 500_000


def sidbe_applicable(data: Dataset) -> str:
    """Empty string when SIDBE can run on ``data``, else the reason it cannot."""
    if not data.has_pair():
        return "it needs the u1/u2 run pair, runs 1 and 2"
    if data.design is None:
        return "the log metadata describe no periodic excitation: samples_per_period, freqs"
    if data.jittered:
        # The lines of a periodic excitation need its periods on one grid. A real axis
        # sampled at irregular instants held each command over its own interval:
        # resampling would invent a different input (a zero-order hold is not
        # band-limited) and interpolated velocity is biased at the excited lines, while
        # the joint estimator is exact at the instants as logged and weights them by
        # their uncertainty. So SIDBE leaves irregular logs to it.
        return "the time stamps are irregular; the FFT needs a fixed sample rate"
    return ""


def identify_sidbe(data: Dataset, *, resonance: bool = False) -> MethodEstimate:
    """SIDBE on a two-run periodic log (see module docstring)."""
    reason = sidbe_applicable(data)
    if reason:
        raise IdentificationError(f"sidbe cannot run: {reason}")
    assert data.design is not None
    r1, r2 = data.run(1), data.run(2)
    if r1.motion is not None and r1.x is not None and r2.x is not None:
        # position only: the FRF of (drift-free, periodic) position is exact, no filter
        n = data.design.samples_per_period
        x1, x2 = detrend_position(r1.x, n), detrend_position(r2.x, n)
        frf = differential_frf(r1.u, x1, r2.u, x2, data.design)
        of_position = True
    else:
        frf = differential_frf(r1.u, r1.v, r2.u, r2.v, data.design)
        of_position = False
    frf_for_fit = frf
    fit = fit_linear_block(frf, resonance=resonance, of_position=of_position)
    notes = list(data.notes)
    if data.closed_loop:
        notes.append(
            "closed-loop log: the differential FRF is taken from the measured total command u, "
            "unbiased at the excited lines, where both runs share the noise-free excitation"
        )
    if fit.resonance_at_bound:
        notes.append("no resonance found within the excited band: fitted without one")
        fit = fit_linear_block(frf_for_fit, resonance=False, of_position=of_position)
    res = (
        Resonance(fit.wn_rad_s, fit.zeta)
        if fit.wn_rad_s is not None and fit.zeta is not None
        else None
    )
    if data.derived:
        fp, fn, sp, sn, sigma = _friction_derived(data, fit.M, fit.B)
    else:
        fp, fn, sp, sn, sigma = _friction_sampled(data, fit.M, fit.B)
    if fp < 0 or fn < 0:
        notes.append("a negative Coulomb level was estimated and clipped to 0")
    if of_position:  # keep the velocity FRF for the plot
        z = np.exp(2j * np.pi * frf.f_hz * frf.dt_s)
        frf = replace(frf, G=frf.G / position_over_velocity(fit.M, fit.B, z, frf.dt_s))
    model = ServoModel(fit.M, fit.B, max(fp, 0.0), max(fn, 0.0), res)
    std = {"M": fit.std_M, "B": fit.std_B, "coulomb_pos": sp, "coulomb_neg": sn}
    return MethodEstimate(model, "sidbe", std, "frf", sigma, tuple(notes), frf)


def _friction_sampled(
    data: Dataset, M: float, B: float
) -> tuple[float, float, float, float, float]:
    dt = data.dt_s
    a = math.exp(-B * dt / M)
    b = (1.0 - a) / B
    vs = [s.v for s in data.segments]
    us = [s.u for s in data.segments]
    ints = [np.full(len(s) - 1, dt) for s in data.segments]
    pairs = select_pairs(vs, us, ints, max_pairs=MAX_PAIRS)
    force = pairs.u - (pairs.v1 - a * pairs.v0) / b
    # noise from the spread of the friction force within each direction
    resid = np.concatenate(
        [force[m] - np.median(force[m]) for m in (pairs.pos, pairs.neg) if np.any(m)]
    )
    sigma = noise_std_from_residual(resid * b, a)
    if sigma > 0:
        pairs = select_pairs(vs, us, ints, threshold=NOISE_SIGMAS * sigma, max_pairs=MAX_PAIRS)
        force = pairs.u - (pairs.v1 - a * pairs.v0) / b
    return (*_levels(force, pairs.pos, pairs.neg), sigma)


def _friction_derived(
    data: Dataset, M: float, B: float
) -> tuple[float, float, float, float, float]:
    forces, pos_l, neg_l = [], [], []
    vmax = max(float(np.max(np.abs(s.v))) for s in data.segments)
    for s in data.segments:
        assert s.motion is not None
        edge = settle_samples(data.fs_hz, s.motion.cutoff_hz)
        uf = filter_command(s.u, data.fs_hz, s.motion.cutoff_hz)
        f = uf - M * s.motion.a - B * s.v
        pos = s.v > 1e-3 * vmax
        neg = s.v < -1e-3 * vmax
        keep = np.zeros(len(s), dtype=bool)
        keep[edge:-edge] = True
        forces.append(f[keep])
        pos_l.append(pos[keep])
        neg_l.append(neg[keep])
    force = np.concatenate(forces)
    return (*_levels(force, np.concatenate(pos_l), np.concatenate(neg_l)), 0.0)


def _levels(
    force: np.ndarray, pos: np.ndarray, neg: np.ndarray
) -> tuple[float, float, float, float]:
    """Mean friction force per direction (magnitudes) and their standard errors."""
    out = []
    for mask, sign in ((pos, 1.0), (neg, -1.0)):
        f = force[mask]
        if f.size == 0:
            out.append((0.0, math.nan))
            continue
        out.append(
            (
                sign * float(f.mean()),
                float(f.std(ddof=1) / math.sqrt(f.size)) if f.size > 1 else math.nan,
            )
        )
    (fp, sp), (fn, sn) = out
    return fp, fn, sp, sn
