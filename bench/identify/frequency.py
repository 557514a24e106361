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
    """

    f_hz: np.ndarray
    G: np.ndarray
    U1: np.ndarray
    U2: np.ndarray
    V1: np.ndarray
    V2: np.ndarray
    dt_s: float
    periods_averaged: int


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
    return FrequencyResponse(
        lines * design.fs_hz / n, (V1 - V2) / dU, U1, U2, V1, V2, 1.0 / design.fs_hz, periods
    )


def zoh_first_order(M: float, B: float, z: np.ndarray, dt_s: float) -> np.ndarray:
    """``b / (z - a)``: the ZOH-sampled ``1/(M s + B)`` at points ``z``."""
    a = math.exp(-B * dt_s / M)
    return (1.0 - a) / B / (z - a)


def model_frf(model, f_hz: np.ndarray, dt_s: float | None = None) -> np.ndarray:
    """Linear-block response of a :class:`~servobench.bench.model.servo.ServoModel` at ``f_hz`` [Hz].

    Continuous ``1/(M s + B)`` (times the resonance) without ``dt_s``; the
    exact ZOH-sampled response (feedback before command) with it.
    """
    f_hz = np.asarray(f_hz, dtype=float)
    if dt_s is None:
        s = 2j * np.pi * f_hz
        g = 1.0 / (model.M * s + model.B)
        return g if model.resonance is None else g * model.resonance.response(s)
    z = np.exp(2j * np.pi * f_hz * dt_s)
    if model.resonance is None:
        return zoh_first_order(model.M, model.B, z, dt_s)
    r = model.resonance
    return _zoh_third_order(model.M, model.B, r.wn_rad_s, r.zeta, z, dt_s)


def _zoh_third_order(
    M: float, B: float, wn: float, zeta: float, z: np.ndarray, dt_s: float
) -> np.ndarray:
    from scipy import signal

    num = [wn**2]
    den = np.polymul([M, B], [1.0, 2 * zeta * wn, wn**2])
    bd, ad, _ = signal.cont2discrete((num, den), dt_s, method="zoh")
    return np.polyval(np.ravel(bd), z) / np.polyval(ad, z)


@dataclass(frozen=True)
class LinearFit:
    """Fitted linear block: ``M``, ``B``, optional resonance ``(wn [rad/s], zeta)``, 1-sigma stds, rms relative misfit."""

    M: float
    B: float
    wn_rad_s: float | None
    zeta: float | None
    std_M: float
    std_B: float
    misfit: float
    resonance_at_bound: bool = False


def position_over_velocity(M: float, B: float, z: np.ndarray, dt_s: float) -> np.ndarray:
    """``X(z)/V(z)`` [s] of the ZOH-sampled first-order plant (position is the integral of velocity).

    From ``X/U = (1/B) (dt/(z-1) - tau (1-a)/(z-a))`` and ``V/U = (1-a)/(B (z-a))``.
    """
    tau = M / B
    a = math.exp(-dt_s / tau)
    return dt_s * (z - a) / ((z - 1.0) * (1.0 - a)) - tau


def fit_linear_block(
    frf: FrequencyResponse, resonance: bool = False, of_position: bool = False
) -> LinearFit:
    """Fit ``1/(M s + B)`` (and a resonance) to the FRF, as its exact ZOH-sampled response.

    A linear least-squares fit of ``G (z - a) = b`` starts a nonlinear fit of
    the relative error ``(G_model - G) / |G|`` over ``log M, log B`` (and
    ``log wn, log zeta``). With ``of_position`` the FRF is position over
    command, and the model's ``X(z)/U(z)`` is fitted.
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
    except (ValueError, np.linalg.LinAlgError, FloatingPointError) as err:
        raise IdentificationError(f"the FRF fit failed: {err}") from None
    return _linear_fit(sol, frf.G.size, bounds)


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
    """``(G_model - G) / |G|`` (real parts, then imaginary) at ``p = log (M, B[, wn, zeta])``."""
    M, B = math.exp(p[0]), math.exp(p[1])
    if resonance:
        g = _zoh_third_order(M, B, math.exp(p[2]), math.exp(p[3]), z, dt)
    else:
        g = zoh_first_order(M, B, z, dt)
    if of_position:
        g = g * position_over_velocity(M, B, z, dt)
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


def _linear_fit(sol: Any, lines: int, bounds: tuple[list[float], list[float]] | None) -> LinearFit:
    """:class:`LinearFit` from a least-squares solution in ``log (M, B[, wn, zeta])``:
    stds from the Jacobian, and whether the resonance ended on a bound."""
    p, r = sol.x, sol.fun
    s2 = float(r @ r) / max(1, r.size - p.size)
    try:
        cov = s2 * np.linalg.inv(sol.jac.T @ sol.jac)
    except np.linalg.LinAlgError:
        cov = np.full((p.size, p.size), np.nan)
    M, B = math.exp(p[0]), math.exp(p[1])
    misfit = math.sqrt(float(r @ r) / max(1, lines))
    wn = zeta = None
    at_bound = False
    if bounds is not None:
        wn, zeta = math.exp(p[2]), math.exp(p[3])
        lo, hi = bounds
        at_bound = bool(
            np.any(np.abs(p[2:] - np.array(lo[2:])) < 1e-6)
            or np.any(np.abs(p[2:] - np.array(hi[2:])) < 1e-6)
        )
    return LinearFit(
        M,
        B,
        wn,
        zeta,
        M * math.sqrt(max(cov[0, 0], 0)),
        B * math.sqrt(max(cov[1, 1], 0)),
        misfit,
        at_bound,
    )
