"""SIDBE as published: differential FRF, parametric fit, then Coulomb friction.

1. Average the steady-state periods of run 1 (``u1``) and run 2
   (``u2 = ratio * u1``) and take the differential FRF
   ``(V1 - V2)/(U1 - U2)`` at the excited lines (:mod:`servobench.bench.identify.frequency`).
2. Fit the linear block ``1/(M s + B)`` -- optionally with the series
   resonance of the paper's eq. (2)-(3) -- to that FRF.
   The drive's action delay ``delay_s`` is fitted jointly, as the phase term
   (the exact delayed hold of :mod:`~servobench.bench.identify.frequency`).
3. With ``M``, ``B`` and the delay fixed, estimate the Coulomb level of each
   direction by least squares of the friction force ``u - M dv/dt - B v``
   over the intervals of each sign, in both runs, using the exact sampled
   form ``u_eff[k] - (v[k+1] - a v[k]) / b``; ``u_eff[k]`` is the constant
   command that moves the block over ``[t_k, t_{k+1})`` as the delayed ones do
   (``u[k]`` without delay). Position-only logs use the filtered command
   shifted by the delay.

The differential pair does not cancel friction exactly (the zero-crossing
times of the two runs differ), so at amplitudes close to the friction level
the estimate is biased; :mod:`servobench.bench.identify.joint` is not. The
stated sigma says how far (:func:`leakage_sigma`): the identified model, its
friction included, is simulated on both runs' commands and put through steps
1-2 again; what comes back off the model is the bias this excitation gives
it (taken again at the model less that bias, nearer the truth, and the larger
kept), added in quadrature to the noise's sigma of ``M``, ``B`` and the
delay, and carried into the Coulomb levels'. A note gives the leakage where it
outweighs the noise. The point estimate stays the published method's.

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

from servobench.bench.identify.covariance import bandwidth, parzen
from servobench.bench.identify.dataset import Dataset
from servobench.bench.identify.delay import effective_command
from servobench.bench.identify.derivative import filter_command, settle_samples
from servobench.bench.identify.estimate import MethodEstimate
from servobench.bench.identify.frequency import (
    detrend_position,
    differential_frf,
    fit_linear_block,
    position_over_velocity,
)
from servobench.bench.identify.regression import noise_std_from_residual, select_pairs
from servobench.bench.model.servo import DELAY_KEY, Resonance, ServoModel
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


def identify_sidbe(data: Dataset, *, resonance: bool = False, leakage: bool = True) -> MethodEstimate:
    """SIDBE on a two-run periodic log (see module docstring). ``leakage=False``: the sigma
    without the friction leakage (a candidate that is only compared on its fit)."""
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
    dt = frf.dt_s
    if fit.delay_s > 0:
        notes.append(
            f"drive action delay {fit.delay_s * 1e3:.3g} ms ({fit.delay_s / dt:.3g} samples, "
            f"1-sigma {fit.std_delay_s / dt:.2g}) identified from the FRF phase"
        )
    if not fit.delay_separable:
        notes.append(
            "the excited band cannot separate the drive's action delay from the plant "
            f"(correlation {fit.delay_correlation:.3f}, 1-sigma {fit.std_delay_s / dt:.2g} samples)"
        )
    if data.derived:
        fp, fn, sp, sn, sigma = _friction_derived(data, fit.M, fit.B, fit.delay_s)
    else:
        fp, fn, sp, sn, sigma = _friction_sampled(data, fit.M, fit.B, fit.delay_s)
    bias = None
    if leakage:
        bias = leakage_sigma(data, ServoModel(fit.M, fit.B, max(fp, 0.0), max(fn, 0.0), res, fit.delay_s),
                             resonance=res is not None)  # fmt: skip
    if bias is not None:
        noise_sd = (fit.std_M, fit.std_B)
        fit = with_bias(fit, bias)
        if abs(bias[0]) > noise_sd[0] or abs(bias[1]) > noise_sd[1]:
            notes.append(
                f"friction leaks into the differential FRF at this amplitude: simulated, it moves M by "
                f"{100 * bias[0] / fit.M:+.2g} % and B by {100 * bias[1] / fit.B:+.2g} %, beyond the "
                "noise's sigma, and the stated sigma includes it; raise the amplitude, or use "
                "--method auto (the joint estimator has no such bias)"
            )
    if data.derived:
        if bias is not None:  # the levels at the biased block: how far the leakage moves them
            bp, bn, *_ = _friction_derived(data, fit.M + bias[0], fit.B + bias[1], max(fit.delay_s + bias[2], 0.0))
            sp, sn = math.hypot(sp, bp - fp), math.hypot(sn, bn - fn)
    else:
        sp, sn = _friction_std(data, fit, NOISE_SIGMAS * sigma if sigma > 0 else 0.0, sigma)
    if fp < 0 or fn < 0:
        notes.append("a negative Coulomb level was estimated and clipped to 0")
    if of_position:  # keep the velocity FRF for the plot
        z = np.exp(2j * np.pi * frf.f_hz * dt)
        ratio = position_over_velocity(fit.M, fit.B, z, dt, fit.delay_s)
        var_G = None if frf.var_G is None else frf.var_G / np.abs(ratio) ** 2
        frf = replace(frf, G=frf.G / ratio, var_G=var_G)
    model = ServoModel(fit.M, fit.B, max(fp, 0.0), max(fn, 0.0), res, fit.delay_s)
    std = {
        "M": fit.std_M,
        "B": fit.std_B,
        "coulomb_pos": sp,
        "coulomb_neg": sn,
        DELAY_KEY: fit.std_delay_s,
    }
    return MethodEstimate(model, "sidbe", std, "frf", sigma, tuple(notes), frf)


def leakage_bias(data: Dataset, model: ServoModel, resonance: bool = False) -> np.ndarray | None:
    """``(dM, dB, d delay_s)``: how far steps 1-2 land off ``model`` when the data are ``model``'s
    own noise-free response to both runs' commands (its friction and delay included), each run
    simulated from its first velocity; None where the simulation or its fit fails."""
    from servobench.bench.identify.simulation import simulate_velocity

    assert data.design is not None
    r1, r2 = data.run(1), data.run(2)
    try:
        v1 = simulate_velocity(model, r1.u, data.dt_s, float(r1.v[0]))
        v2 = simulate_velocity(model, r2.u, data.dt_s, float(r2.v[0]))
        back = fit_linear_block(differential_frf(r1.u, v1, r2.u, v2, data.design), resonance=resonance)
    except (IdentificationError, ValueError, FloatingPointError):
        return None
    bias = np.array([back.M - model.M, back.B - model.B, back.delay_s - model.delay_s])
    return bias if np.all(np.isfinite(bias)) else None


#: Fixed-point steps of :func:`leakage_sigma` towards the model whose leakage gives the estimate.
LEAKAGE_STEPS = 4


def leakage_sigma(data: Dataset, model: ServoModel, resonance: bool = False) -> np.ndarray | None:
    """The leakage to state in the sigma of ``(M, B, delay_s)``, or None where it cannot be
    simulated.

    :func:`leakage_bias` at the estimate gives the bias there; but the bias that made the
    estimate arose at the truth, where it may differ (a bias of 100 % in ``B`` on a short
    pair). So the model ``m`` whose own leakage lands on the estimate, ``m + bias(m) =
    estimate``, is sought by fixed-point steps ``m <- estimate - bias(m)``
    (:data:`LEAKAGE_STEPS`), and the larger of ``estimate - m`` and the bias at the estimate
    is stated, per parameter."""
    at_estimate = leakage_bias(data, model, resonance)
    if at_estimate is None:
        return None
    total, bias = at_estimate, at_estimate
    for _ in range(LEAKAGE_STEPS):
        M, B = model.M - bias[0], model.B - bias[1]
        if not (M > 0 and B > 0):  # the bias is as large as the estimate: no model lands there
            break
        nearer = replace(model, M=M, B=B, delay_s=max(model.delay_s - bias[2], 0.0))
        step = leakage_bias(data, nearer, resonance)
        if step is None:
            break
        total, bias = np.array([model.M - nearer.M, model.B - nearer.B, model.delay_s - nearer.delay_s]), step
    last = np.array(bias)  # the leakage at the last model tried: estimate - that model, one step on
    stated = np.where(np.abs(total) > np.abs(at_estimate), total, at_estimate)
    return np.where(np.abs(last) > np.abs(stated), last, stated)


def with_bias(fit, bias: np.ndarray):
    """``fit`` with ``bias`` (:func:`leakage_bias`) in its sigma and covariance, in quadrature."""
    cov = None if fit.cov is None else fit.cov + np.outer(bias, bias)
    return replace(
        fit,
        std_M=math.hypot(fit.std_M, bias[0]),
        std_B=math.hypot(fit.std_B, bias[1]),
        std_delay_s=math.hypot(fit.std_delay_s, bias[2]) if math.isfinite(fit.std_delay_s) else fit.std_delay_s,
        cov=cov,
    )


def _friction_sampled(
    data: Dataset, M: float, B: float, delay_s: float = 0.0
) -> tuple[float, float, float, float, float]:
    dt = data.dt_s
    a = math.exp(-B * dt / M)
    b = -math.expm1(-B * dt / M) / B  # (1 - a) / B without the cancellation: never 0
    vs = [s.v for s in data.segments]
    # the command held over each interval that moves the block as the delayed ones do
    # (padded to n: the pairs read u[k] for k < n - 1 only)
    us = [_pad(effective_command(s.u, dt, delay_s, M / B, offsets_s=s.act_offset_s)) for s in data.segments]
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


def _friction_std(data: Dataset, fit, threshold: float, sigma: float) -> tuple[float, float]:
    """1-sigma of the Coulomb levels of :func:`_friction_sampled` (pairs beyond ``threshold``).

    A level is the mean of ``u_eff[k] - (v[k+1] - a v[k]) / b`` over its pairs, so
    it carries (1) the error of ``M``, ``B`` and the delay, propagated through its
    gradient (finite differences, the pairs held) with the FRF fit's covariance,
    and (2) the velocity noise, a linear functional ``sum c_k e_k`` of it whose
    variance is ``sum_l gamma(l) sum_k c_k c_k+l``: ``gamma`` the noise's
    autocovariance, read from the spread of the steady periods about their mean
    (Parzen-tapered, :func:`~servobench.bench.identify.covariance.bandwidth`), so
    coloured noise counts at its true weight. The mean of the pairs' spread over
    root N (what this replaces) treats the pairs as independent: with ``a``
    close to 1 their noise nearly cancels along each stretch of motion, while the
    error of ``M`` and ``B`` goes uncounted.
    """
    dt = data.dt_s
    segments = [(s.v, effective_command(s.u, dt, fit.delay_s, fit.M / fit.B)) for s in data.segments]
    masks = [((v[:-1] > threshold) & (v[1:] > threshold), (v[:-1] < -threshold) & (v[1:] < -threshold))
             for v, _ in segments]  # fmt: skip

    def levels(M: float, B: float, delay_s: float) -> np.ndarray:
        a = math.exp(-B * dt / M)
        b = -math.expm1(-B * dt / M) / B
        sums, counts = np.zeros(2), np.zeros(2)
        for (v, _), s, m in zip(segments, data.segments, masks, strict=True):
            u = effective_command(s.u, dt, delay_s, M / B)[: v.size - 1]
            f = u - (v[1:] - a * v[:-1]) / b
            for i in (0, 1):
                sums[i] += float(np.sum(f[m[i]]))
                counts[i] += np.count_nonzero(m[i])
        return sums / np.maximum(counts, 1) * np.array([1.0, -1.0])

    counts = np.array([sum(np.count_nonzero(m[i]) for m in masks) for i in (0, 1)], dtype=float)
    var = np.zeros(2)
    cov = fit.cov
    if cov is not None and np.all(np.isfinite(cov)):
        p = np.array([fit.M, fit.B, fit.delay_s])
        grad = np.zeros((2, 3))
        for j in range(3):
            h = 1e-6 * p[j] if j < 2 else 1e-3 * dt
            up, down = p.copy(), p.copy()
            up[j] += h
            down[j] -= h if (j < 2 or p[j] - h >= min(0.0, data.min_delay_s)) else 0.0
            grad[:, j] = (levels(*up) - levels(*down)) / (up[j] - down[j])
        var += np.einsum("ij,jk,ik->i", grad, cov, grad)
    a = math.exp(-fit.B * dt / fit.M)
    b = -math.expm1(-fit.B * dt / fit.M) / fit.B
    gamma = _noise_autocovariance(data, sigma)
    weights = parzen(np.arange(gamma.size) / gamma.size)
    for m in masks:
        for i in (0, 1):
            if counts[i] == 0:
                continue
            c = np.zeros(m[i].size + 1)
            k = np.flatnonzero(m[i])
            np.add.at(c, k, a / (b * counts[i]))
            np.add.at(c, k + 1, -1.0 / (b * counts[i]))
            var[i] += gamma[0] * float(c @ c) + 2.0 * sum(
                weights[lag] * gamma[lag] * float(c[lag:] @ c[:-lag]) for lag in range(1, min(gamma.size, c.size)))
    sd = np.sqrt(np.clip(var, 0.0, None))
    return (float(sd[0]) if counts[0] else math.nan, float(sd[1]) if counts[1] else math.nan)


def _noise_autocovariance(data: Dataset, sigma: float) -> np.ndarray:
    """Autocovariance of the velocity noise at lags ``0 .. L-1`` [units^2/s^2], from each
    run's steady periods about their mean (white ``sigma`` with fewer than two)."""
    assert data.design is not None
    n = data.design.samples_per_period
    rows = []
    for s in data.segments:
        periods = len(s) // n - 1
        if periods < 2:
            continue
        steady = s.v[n : (1 + periods) * n].reshape(periods, n)
        rows.extend((steady - steady.mean(axis=0)) * math.sqrt(periods / (periods - 1)))
    if not rows:
        return np.array([sigma**2])
    e = np.concatenate(rows)
    bounds = np.cumsum([r.size for r in rows])
    lags = bandwidth(e, bounds)
    gamma = np.zeros(lags)
    for lag in range(lags):
        gamma[lag] = sum(float(r[lag:] @ r[: r.size - lag]) for r in rows) / e.size
    return gamma


def _pad(u_eff: np.ndarray) -> np.ndarray:
    return np.append(u_eff, u_eff[-1:] if u_eff.size else 0.0)


def _friction_derived(
    data: Dataset, M: float, B: float, delay_s: float = 0.0
) -> tuple[float, float, float, float, float]:
    """Friction from filtered position-derived motion; the filtered command is shifted
    by ``delay_s`` by linear interpolation between samples (the filtered command is
    smooth at the sample rate, so a fractional shift by interpolation is accurate)."""
    forces, pos_l, neg_l = [], [], []
    vmax = max(float(np.max(np.abs(s.v))) for s in data.segments)
    for s in data.segments:
        assert s.motion is not None
        edge = settle_samples(data.fs_hz, s.motion.cutoff_hz)
        uf = filter_command(s.u, data.fs_hz, s.motion.cutoff_hz)
        if delay_s > 0:
            k = np.arange(len(uf), dtype=float)
            uf = np.interp(k - delay_s * data.fs_hz, k, uf)
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
