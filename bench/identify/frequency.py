"""Frequency-domain part of SIDBE: steady-state spectra, differential FRF, parametric fit.

The runs of a SIDBE log repeat a periodic command. The first period is the
transient; the remaining periods are averaged (noise drops with their
number) and transformed with the FFT. At each excited line ``k``::

    G_k = (V1_k - V2_k) / (U1_k - U2_k)

which cancels the friction terms that are common to both runs. A linear
block ``1/(M s + B)`` (optionally times the series resonance
``wn^2/(s^2 + 2 zeta wn s + wn^2)``) is fitted to ``G_k`` as the exact
zero-order-hold sampled response: feedback ``v[k]`` is sampled before
``u[k]`` acts, so the first-order block is ``b / (z - a)`` with
``a = exp(-B dt/M)`` and ``b = (1 - a)/B``. Frequencies in Hz.

The drive's action delay ``d = (m + f) dt`` (``0 <= f < 1``; ``u[k]`` acts
over ``[t_k + d, t_{k+1} + d)``, :attr:`~servobench.bench.model.servo.ServoModel.delay_s`)
is fitted with them, as the phase term. Over ``[t_k, t_{k+1})`` the command
``u[k-m-1]`` acts for ``f dt``, then ``u[k-m]``, so the sampled block is::

    V/U = z^-m (c0 z + c1) / (z (z - a)),
    c0 = (1 - a^(1-f))/B,  c1 = (a^(1-f) - a)/B       (c0 + c1 = b)

-- exact, continuous in ``d``, with a kink in its slope at whole samples
(:func:`zoh_first_order`; position: :func:`zoh_position`; with the resonance
the same two-piece hold in state space).

Each line's noise variance comes from the spread of the steady periods
(``FrequencyResponse.var_G``); the fit's standard deviations use it, since
the relative misfit does not weight the lines by their noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from servobench.bench.procedure.excitation import ExcitationDesign
from servobench.errors import IdentificationError


@dataclass(frozen=True)
class FrequencyResponse:
    """Measured response at the excited lines; arrays of shape ``(m,)``.

    Attributes
    ----------
    f_hz : ndarray
        Line frequencies [Hz].
    G : ndarray (complex)
        Differential FRF ``(V1 - V2)/(U1 - U2)`` [velocity units per command unit].
    U1, U2, V1, V2 : ndarray (complex)
        Line spectra of the averaged steady-state periods (DFT / samples).
    dt_s : float
        Sample interval [s] (the FRF is that of the sampled system).
    periods_averaged : int
    var_G : ndarray or None
        Noise variance of ``G`` at each line (``E|dG|^2``), from the spread of the
        steady-state periods of each run; None with fewer than two of them.
    """

    f_hz: np.ndarray
    G: np.ndarray
    U1: np.ndarray
    U2: np.ndarray
    V1: np.ndarray
    V2: np.ndarray
    dt_s: float
    periods_averaged: int
    var_G: np.ndarray | None = None


def steady_average(
    y: np.ndarray, samples_per_period: int, first: int = 1, last: int | None = None
) -> np.ndarray:
    """Mean over periods ``first .. last-1`` of ``y`` (shape ``(samples_per_period,)``)."""
    n = samples_per_period
    whole = len(y) // n
    last = whole if last is None else min(last, whole)
    if last <= first:
        raise IdentificationError(
            f"need at least {first + 1} whole periods of {n} samples, the run has {whole}"
        )
    return np.asarray(y[first * n : last * n], dtype=float).reshape(last - first, n).mean(axis=0)


def line_spectrum(y_period: np.ndarray, lines: np.ndarray) -> np.ndarray:
    """DFT of one period at bins ``lines``, divided by the period length."""
    return np.fft.rfft(y_period)[lines] / len(y_period)


def detrend_position(x: np.ndarray, samples_per_period: int) -> np.ndarray:
    """Remove the steady drift of position so that it becomes periodic.

    In periodic steady state ``x[k + N] = x[k] + D``; ``D`` is estimated from
    the end of the first period on, and ``x[k] - D k / N`` is returned.
    """
    n = samples_per_period
    x = np.asarray(x, dtype=float)
    if len(x) < 2 * n:
        raise IdentificationError("position detrending needs two whole periods")
    k0 = n - 1
    drift = float(np.mean(x[k0 + n :] - x[k0 : len(x) - n]))
    return x - drift * np.arange(len(x)) / n


def differential_frf(
    u1: np.ndarray,
    v1: np.ndarray,
    u2: np.ndarray,
    v2: np.ndarray,
    design: ExcitationDesign,
    first: int = 1,
) -> FrequencyResponse:
    """The differential FRF of two runs of one design (steady-state periods ``first..``).

    ``v1``, ``v2`` may also be detrended positions (:func:`detrend_position`):
    the result is then position over command.
    """
    n = design.samples_per_period
    lines = design.lines
    spectra = [line_spectrum(steady_average(y, n, first), lines) for y in (u1, v1, u2, v2)]
    U1, V1, U2, V2 = spectra
    dU = U1 - U2
    if np.any(np.abs(dU) <= 1e-12 * np.max(np.abs(U1))):
        raise IdentificationError("u1 and u2 do not differ at the excited lines; is ratio < 1?")
    periods = len(u1) // n - first
    G = (V1 - V2) / dU
    var_num = _frf_variance(G, (u1, v1), (u2, v2), n, lines, first)
    var_G = None if var_num is None else var_num / np.abs(dU) ** 2
    return FrequencyResponse(
        lines * design.fs_hz / n, G, U1, U2, V1, V2, 1.0 / design.fs_hz, periods, var_G
    )


def _frf_variance(
    G: np.ndarray,
    run1: tuple[np.ndarray, np.ndarray],
    run2: tuple[np.ndarray, np.ndarray],
    n: int,
    lines: np.ndarray,
    first: int,
) -> np.ndarray | None:
    """Noise variance of the averaged ``V1 - V2 - G (U1 - U2)`` at the lines (None: too few periods).

    Per run, ``e_p = V_p - G U_p`` over its steady periods ``p``: its sample
    variance over the periods, divided by their number, is the variance of the
    run's share of the averaged numerator (noise on ``u`` included, to first order).
    """
    total = np.zeros(lines.size)
    for u, y in (run1, run2):
        count = min(len(u), len(y)) // n - first
        if count < 2:
            return None
        span = slice(first * n, (first + count) * n)
        per = [np.fft.rfft(np.asarray(w[span], dtype=float).reshape(count, n), axis=1)[:, lines] / n
               for w in (u, y)]  # fmt: skip
        e = per[1] - G * per[0]
        total += np.sum(np.abs(e - e.mean(axis=0)) ** 2, axis=0) / (count - 1) / count
    return total


def split_delay(delay_samples: float) -> tuple[int, float]:
    """``(m, f)``: the whole samples and the fraction ``0 <= f < 1`` of a delay in samples."""
    m = int(math.floor(delay_samples))
    return m, float(delay_samples - m)


def zoh_first_order(
    M: float, B: float, z: np.ndarray, dt_s: float, delay_s: float = 0.0
) -> np.ndarray:
    """The ZOH-sampled ``1/(M s + B)`` at points ``z``: ``b / (z - a)``, and with the
    action delay ``delay_s`` [s] ``z^-m (c0 z + c1) / (z (z - a))`` (module docstring)."""
    a = math.exp(-B * dt_s / M)
    if delay_s <= 0:
        return (1.0 - a) / B / (z - a)
    m, f = split_delay(delay_s / dt_s)
    rate = B * dt_s / M
    af = math.exp(-rate * (1.0 - f))
    c0 = -math.expm1(-rate * (1.0 - f)) / B  # (1 - a^(1-f))/B without cancellation
    c1 = -af * math.expm1(-rate * f) / B  # (a^(1-f) - a)/B
    return z ** (-m) * (c0 * z + c1) / (z * (z - a))


def zoh_position(
    M: float, B: float, z: np.ndarray, dt_s: float, delay_s: float = 0.0
) -> np.ndarray:
    """``X(z)/U(z)`` [position units per command unit] of the ZOH-sampled ``1/(s (M s + B))``.

    ``1/(s (M s + B)) = (1/B)/s - tau/(M s + B)`` (``tau = M/B``); under the
    delayed hold the integrator's part is ``z^-m dt ((1-f) z + f) / (B z (z - 1))``
    and the first-order part ``tau`` times :func:`zoh_first_order`.
    """
    if delay_s <= 0:
        return zoh_first_order(M, B, z, dt_s) * position_over_velocity(M, B, z, dt_s)
    m, f = split_delay(delay_s / dt_s)
    integrator = z ** (-m) * dt_s * ((1.0 - f) * z + f) / (B * z * (z - 1.0))
    return integrator - M / B * zoh_first_order(M, B, z, dt_s, delay_s)


def model_frf(model, f_hz: np.ndarray, dt_s: float | None = None) -> np.ndarray:
    """Linear-block response of a :class:`~servobench.bench.model.servo.ServoModel` at ``f_hz`` [Hz].

    Continuous ``exp(-s delay_s)/(M s + B)`` (times the resonance) without
    ``dt_s``; the exact ZOH-sampled response (feedback before command, the
    command acting ``model.delay_s`` after its instant) with it.
    """
    f_hz = np.asarray(f_hz, dtype=float)
    delay_s = model.delay_s
    if dt_s is None:
        s = 2j * np.pi * f_hz
        g = np.exp(-s * delay_s) / (model.M * s + model.B)
        return g if model.resonance is None else g * model.resonance.response(s)
    z = np.exp(2j * np.pi * f_hz * dt_s)
    if model.resonance is None:
        return zoh_first_order(model.M, model.B, z, dt_s, delay_s)
    r = model.resonance
    return _zoh_third_order(model.M, model.B, r.wn_rad_s, r.zeta, z, dt_s, delay_s)


def _zoh_third_order(
    M: float, B: float, wn: float, zeta: float, z: np.ndarray, dt_s: float, delay_s: float = 0.0
) -> np.ndarray:
    from scipy import signal

    if delay_s > 0:
        # states v, y, y'/wn (output y: the mode's response to v), all of one scale
        A = np.array([[-B / M, 0.0, 0.0], [0.0, 0.0, wn], [wn, -wn, -2.0 * zeta * wn]])
        Bi = np.array([[1.0 / M], [0.0], [0.0]])
        return _delayed_hold(A, Bi, np.array([[0.0, 1.0, 0.0]]), z, dt_s, delay_s)
    num = [wn**2]
    den = np.polymul([M, B], [1.0, 2 * zeta * wn, wn**2])
    bd, ad, _ = signal.cont2discrete((num, den), dt_s, method="zoh")
    return np.polyval(np.ravel(bd), z) / np.polyval(ad, z)


def _delayed_hold(
    A: np.ndarray, Bi: np.ndarray, C: np.ndarray, z: np.ndarray, dt_s: float, delay_s: float
) -> np.ndarray:
    """``z^-m C (z I - Phi)^-1 (G0 + G1 / z)``: a strictly proper state-space block
    ``(A, Bi, C)`` under the hold delayed by ``(m + f) dt``, where ``u[k-m-1]`` acts for
    ``f dt`` (``G1``), then ``u[k-m]`` for ``(1 - f) dt`` (``G0``)."""
    from scipy.linalg import expm

    n = A.shape[0]
    m, f = split_delay(delay_s / dt_s)

    def hold(h: float) -> tuple[np.ndarray, np.ndarray]:
        aug = np.zeros((n + 1, n + 1))
        aug[:n, :n], aug[:n, n:] = A * h, Bi * h
        e = expm(aug)
        return e[:n, :n], e[:n, n:]

    phi = expm(A * dt_s)
    late, g0 = hold((1.0 - f) * dt_s)
    g1 = late @ hold(f * dt_s)[1]
    zz = z[:, None, None]
    x = np.linalg.solve(zz * np.eye(n) - phi, g0[None] + g1[None] / zz)
    return z ** (-m) * (C @ x)[:, 0, 0]


#: Largest action delay the fit considers [samples]: the scan's range and the fit's bound.
MAX_DELAY_SAMPLES = 8.0
#: Step of the delay scan that starts the fit [samples] (well inside a phase wrap at Nyquist).
DELAY_SCAN_STEP = 0.25
#: A fitted delay below this [samples] is the bound: the delay-free fit stands.
DELAY_ZERO = 1e-6
#: Largest |correlation| of the delay with another parameter for the delay to be separable.
DELAY_CORRELATION_LIMIT = 0.99


@dataclass(frozen=True)
class LinearFit:
    """Fitted linear block, 1-sigma stds, rms relative misfit.

    Attributes
    ----------
    M, B : float
    wn_rad_s, zeta : float or None
        Series resonance [rad/s], damping; None without one.
    std_M, std_B : float
    misfit : float
    resonance_at_bound : bool
        The mode ended on a bound of its search range.
    delay_s : float
        Action delay [s] (0 when it ended on its bound 0, or was not fitted).
    std_delay_s : float
        Its 1-sigma [s]; nan when it was not fitted.
    delay_correlation : float
        Largest |correlation| of the delay with another parameter (nan: not fitted).
    delay_separable : bool
        False when the excited band cannot tell the delay from the plant: its
        correlation exceeds :data:`DELAY_CORRELATION_LIMIT`, its sigma exceeds
        one sample, or it ended on :data:`MAX_DELAY_SAMPLES`.
    cov : ndarray, shape (3, 3), or None
        Covariance of ``(M, B, delay_s)`` [natural units; s]; the delay's row and
        column are 0 when it was not fitted.
    """

    M: float
    B: float
    wn_rad_s: float | None
    zeta: float | None
    std_M: float
    std_B: float
    misfit: float
    resonance_at_bound: bool = False
    delay_s: float = 0.0
    std_delay_s: float = math.nan
    delay_correlation: float = math.nan
    delay_separable: bool = True
    cov: np.ndarray | None = None


def position_over_velocity(
    M: float, B: float, z: np.ndarray, dt_s: float, delay_s: float = 0.0
) -> np.ndarray:
    """``X(z)/V(z)`` [s] of the ZOH-sampled first-order plant (position is the integral of velocity).

    From ``X/U = (1/B) (dt/(z-1) - tau (1-a)/(z-a))`` and ``V/U = (1-a)/(B (z-a))``;
    with an action delay ``delay_s`` [s], :func:`zoh_position` over :func:`zoh_first_order`.
    """
    if delay_s > 0:
        return zoh_position(M, B, z, dt_s, delay_s) / zoh_first_order(M, B, z, dt_s, delay_s)
    tau = M / B
    a = math.exp(-dt_s / tau)
    return dt_s * (z - a) / ((z - 1.0) * (1.0 - a)) - tau


def fit_linear_block(
    frf: FrequencyResponse,
    resonance: bool = False,
    of_position: bool = False,
    delay: bool = True,
) -> LinearFit:
    """Fit ``1/(M s + B)`` (and a resonance, and the action delay) to the FRF, as its
    exact ZOH-sampled response.

    A linear least-squares fit of ``G (z - a) = b`` starts a nonlinear fit of
    the relative error ``(G_model - G) / |G|`` over ``log M, log B`` (and
    ``log wn, log zeta``): the delay-free fit. With ``delay`` the delay ``q``
    [samples] is then scanned over ``0 .. MAX_DELAY_SAMPLES`` in steps of
    :data:`DELAY_SCAN_STEP` (``log M, log B`` refitted at each, the mode held),
    and from the best point all parameters and ``q`` in ``[0, MAX_DELAY_SAMPLES]``
    are fitted jointly (trust-region reflective). A delay ending within
    :data:`DELAY_ZERO` of 0 leaves the delay-free fit unchanged. With
    ``of_position`` the FRF is position over command, and the model's
    ``X(z)/U(z)`` is fitted.
    """
    from scipy.optimize import least_squares

    if frf.G.size < (4 if resonance else 2):
        raise IdentificationError(f"{frf.G.size} excited lines are too few for the fit")
    dt = frf.dt_s
    z = np.exp(2j * np.pi * frf.f_hz * dt)
    # the start works on velocity: trapezoidal velocity from position, for the start only
    G_start = frf.G * 2 * (z - 1) / (dt * (1 + z)) if of_position else frf.G
    M0, B0 = _start_values(G_start, z, dt)
    p0 = [math.log(M0), math.log(B0)]
    args = (z, dt, frf.G, resonance, of_position)
    try:
        if resonance:
            sol, bounds = _fit_with_resonance(frf.f_hz, G_start, z, dt, (M0, B0), args)
        else:
            sol, bounds = least_squares(_relative_misfit, p0, method="lm", args=args), None
        x = np.append(sol.x, 0.0)
        if delay:
            joint = _fit_delay(sol.x, args, bounds)
            if joint.x[-1] >= DELAY_ZERO and joint.cost < sol.cost:
                x = joint.x
    except (ValueError, np.linalg.LinAlgError, ArithmeticError) as err:
        raise IdentificationError(f"the FRF fit failed: {err}") from None
    return _linear_fit(x, args, bounds, delay, frf.var_G)


def _fit_delay(p_free: np.ndarray, args: tuple, bounds: tuple | None) -> Any:
    """The joint fit of ``p = (log M, log B[, log wn, log zeta], q)``, ``q`` the delay
    [samples], started at the best point of a scan over ``q`` from the delay-free ``p_free``."""
    from scipy.optimize import least_squares

    def at(q: float):
        def fun(mb: np.ndarray) -> np.ndarray:
            return _relative_misfit(np.concatenate((mb, p_free[2:], [q])), *args)

        return fun

    best_q, best_cost, best_p = 0.0, math.inf, p_free
    mb = p_free[:2]
    for q in np.arange(0.0, MAX_DELAY_SAMPLES + 1e-9, DELAY_SCAN_STEP):
        try:
            local = least_squares(at(float(q)), mb, method="lm")
        except (ValueError, ArithmeticError):  # this delay drove M or B out of range
            continue
        mb = local.x  # continuation: the next delay starts here
        if local.cost < best_cost:
            best_q, best_cost = float(q), float(local.cost)
            best_p = np.concatenate((local.x, p_free[2:]))
    lo = list(bounds[0]) if bounds else [-np.inf, -np.inf]
    hi = list(bounds[1]) if bounds else [np.inf, np.inf]
    lo, hi = lo + [0.0], hi + [MAX_DELAY_SAMPLES]
    x0 = np.clip(np.append(best_p, best_q), lo, hi)
    return least_squares(
        _relative_misfit, x0, bounds=(lo, hi), method="trf", args=args,
        xtol=1e-12, ftol=1e-12, gtol=1e-12,
    )  # fmt: skip


def _start_values(G: np.ndarray, z: np.ndarray, dt: float) -> tuple[float, float]:
    """``M, B`` from the linear least-squares fit of ``(z - a) - b / G = 0`` to a velocity
    FRF (relative to ``|z - a| ~ 1``), or from the gain of the lowest line when that fit
    is not a damped plant."""
    A = np.column_stack((-np.ones_like(G), -1.0 / G))
    A_ri = np.vstack((A.real, A.imag))
    rhs_ri = np.concatenate((-z.real, -z.imag))
    (a0, b0), *_ = np.linalg.lstsq(A_ri, rhs_ri, rcond=None)
    a0, b0 = float(np.real(a0)), float(np.real(b0))
    if not (0.0 < a0 < 1.0 and b0 > 0):
        # fall back to DC-ish guesses: gain of the lowest line, corner at mid band
        b0 = abs(G[0]) * (1 - 0.99)
        a0 = 0.99
    B0 = (1.0 - a0) / b0
    return -B0 * dt / math.log(a0), B0


def _relative_misfit(
    p: np.ndarray,
    z: np.ndarray,
    dt: float,
    G: np.ndarray,
    resonance: bool,
    of_position: bool,
) -> np.ndarray:
    """``(G_model - G) / |G|`` (real parts, then imaginary) at ``p = log (M, B[, wn, zeta])``,
    then optionally the delay ``q`` [samples] (0 without it)."""
    M, B = math.exp(p[0]), math.exp(p[1])
    base = 4 if resonance else 2
    delay_s = float(p[base]) * dt if len(p) > base else 0.0
    if resonance:
        g = _zoh_third_order(M, B, math.exp(p[2]), math.exp(p[3]), z, dt, delay_s)
        if of_position:
            g = g * position_over_velocity(M, B, z, dt, delay_s)
    elif of_position:
        g = zoh_position(M, B, z, dt, delay_s)
    else:
        g = zoh_first_order(M, B, z, dt, delay_s)
    e = (g - G) / np.abs(G)
    return np.concatenate((e.real, e.imag))


def _fit_with_resonance(
    f_hz: np.ndarray,
    G_start: np.ndarray,
    z: np.ndarray,
    dt: float,
    start: tuple[float, float],
    args: tuple,
) -> tuple[Any, tuple[list[float], list[float]]]:
    """The best of several bounded fits with a resonance, and the bounds ``(lo, hi)``.

    The mode is kept between a tenth of the lowest line and 0.45 fs, its damping in
    [1e-3, 10]; the fits start at the line where the velocity FRF ``G_start`` most
    exceeds the first-order start ``(M, B)``, beyond the band and mid band, each
    lightly and well damped. ``args`` are those of :func:`_relative_misfit`.
    """
    from scipy.optimize import least_squares

    lo = [-np.inf, -np.inf, math.log(2 * math.pi * f_hz[0] / 10), math.log(1e-3)]
    hi = [np.inf, np.inf, math.log(2 * math.pi * 0.45 / dt), math.log(10.0)]
    p0 = [math.log(start[0]), math.log(start[1])]
    ratio = np.abs(G_start / zoh_first_order(start[0], start[1], z, dt))
    guesses = [f_hz[int(np.argmax(ratio))], f_hz[-1] * 2.0, f_hz[len(f_hz) // 2]]
    best = None
    for f_guess in guesses:
        for zeta0 in (0.05, 0.3):
            x0 = np.clip(p0 + [math.log(2 * math.pi * f_guess), math.log(zeta0)], lo, hi)
            x0 = np.minimum(np.maximum(x0, np.array(lo) + 1e-9), np.array(hi) - 1e-9)
            cand = least_squares(_relative_misfit, x0, bounds=(lo, hi), method="trf", args=args)
            if best is None or cand.cost < best.cost:
                best = cand
    return best, (lo, hi)


def _linear_fit(
    p: np.ndarray,
    args: tuple,
    bounds: tuple[list[float], list[float]] | None,
    delay: bool,
    var_G: np.ndarray | None = None,
) -> LinearFit:
    """:class:`LinearFit` at ``p = log (M, B[, wn, zeta]), q``.

    The covariance comes from a forward-difference Jacobian ``J`` (over ``q`` too
    when the delay was fitted). The relative misfit does not weight the lines by
    their noise, so with the FRF's noise variance ``var_G`` it is the sandwich
    ``H^-1 J' W J H^-1`` (``H = J'J``, ``W`` the residuals' noise variances) plus
    ``s_x^2 H^-1`` for the residual's excess ``s_x^2`` over that noise (a
    systematic misfit, such as friction's at low amplitude); without ``var_G``,
    ``s^2 H^-1``. Also: whether the resonance
    ended on a bound, and whether the delay is separable.
    """
    fun_p = p if delay else p[:-1]
    r = _relative_misfit(fun_p, *args)
    jac = _jacobian(fun_p, args, r)
    cov = _covariance(jac, r, args[2], var_G)
    lines = r.size // 2
    M, B = math.exp(p[0]), math.exp(p[1])
    misfit = math.sqrt(float(r @ r) / max(1, lines))
    wn = zeta = None
    at_bound = False
    if bounds is not None:
        wn, zeta = math.exp(p[2]), math.exp(p[3])
        lo, hi = np.array(bounds[0][2:4]), np.array(bounds[1][2:4])
        at_bound = bool(np.any(np.abs(p[2:4] - lo) < 1e-6) or np.any(np.abs(p[2:4] - hi) < 1e-6))
    dt = args[1]
    q = float(p[-1])
    std_q, corr = math.nan, math.nan
    separable = True
    if delay:
        std_q = math.sqrt(max(cov[-1, -1], 0.0))
        # how the delay trades against the plant is the design's, not the residual's: an exact
        # fit (a residual of 0, a covariance of 0) reads it from (J'J)^-1 alone
        shape = cov if np.all(np.diag(cov) > 0) else _unscaled(jac)
        d = np.sqrt(np.abs(np.diag(shape)))
        with np.errstate(divide="ignore", invalid="ignore"):
            corr = float(np.max(np.abs(shape[-1, :-1] / (d[-1] * d[:-1]))))
        separable = bool(
            corr <= DELAY_CORRELATION_LIMIT and std_q <= 1.0 and q < MAX_DELAY_SAMPLES - DELAY_ZERO
        )  # a nan correlation is not separable
    # (log M, log B[, mode], q) -> (M, B, delay_s)
    rows = [0, 1, cov.shape[0] - 1] if delay else [0, 1]
    scale = np.array([M, B, dt])[: len(rows)]
    natural = np.zeros((3, 3))
    natural[: len(rows), : len(rows)] = cov[np.ix_(rows, rows)] * np.outer(scale, scale)
    return LinearFit(
        M,
        B,
        wn,
        zeta,
        M * math.sqrt(max(cov[0, 0], 0)),
        B * math.sqrt(max(cov[1, 1], 0)),
        misfit,
        at_bound,
        q * dt,
        std_q * dt,
        corr,
        separable,
        natural,
    )


def _unscaled(jac: np.ndarray) -> np.ndarray:
    """``(J'J)^-1``: the covariance's shape without its scale (NaN where singular)."""
    try:
        return np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        return np.full((jac.shape[1], jac.shape[1]), np.nan)


def _covariance(
    jac: np.ndarray, r: np.ndarray, G: np.ndarray, var_G: np.ndarray | None
) -> np.ndarray:
    """Parameter covariance of the relative-misfit fit (see :func:`_linear_fit`)."""
    size = jac.shape[1]
    h_inv = _unscaled(jac)
    if not np.all(np.isfinite(h_inv)):
        return h_inv
    dof = max(1, r.size - size)
    if var_G is not None and np.all(np.isfinite(var_G)):
        # noise (known per line) plus whatever the residual holds beyond it, as relative misfit
        w = np.tile(var_G / (2.0 * np.abs(G) ** 2), 2)  # per real and imaginary part
        excess = max(0.0, float(r @ r) - float(w.sum()) * dof / r.size) / dof
        return h_inv @ (jac.T @ (w[:, None] * jac)) @ h_inv + excess * h_inv
    return float(r @ r) / dof * h_inv


def _jacobian(p: np.ndarray, args: tuple, r: np.ndarray) -> np.ndarray:
    """Forward-difference Jacobian of :func:`_relative_misfit` at ``p`` (residual ``r``);
    forward keeps a delay on its bound 0 feasible."""
    jac = np.empty((r.size, p.size))
    for i in range(p.size):
        step = 1.49e-8 * max(1.0, abs(float(p[i])))
        q = p.copy()
        q[i] += step
        jac[:, i] = (_relative_misfit(q, *args) - r) / step
    return jac
