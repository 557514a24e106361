"""Friction feed-forward and velocity-loop PI design from the identified model (pure).

Plant ``G(s) = 1/(M s + B)`` from command ``u`` [command units] to velocity
``v`` [velocity units/s], sampled with period ``T`` under zero-order hold,
with ``d`` cycles of delay (a lock-step exchange: the command computed from
``v_k`` acts from ``t_{k+1}``, ``d = 1``)::

    G(z) = (1 - a) / (B (z - a)),   a = exp(-B T / M)
    C(z) = Kp + Ki T z / (z - 1)    (PI, backward-Euler integrator; Ki = Kp / Ti)
    L(z) = C(z) G(z) z^-d

Design (phase margin): the PI zero sits a fixed ratio below the crossover,
``Ti = pi_zero_ratio / wc``, or cancels the plant pole when that is faster
(``Ti = M / B`` if smaller: a plant that is nearly a static gain gets a
nearly integral controller), ``Kp`` puts ``|L| = 1`` at ``wc``, and ``wc`` is
the largest crossover whose *discrete* phase margin (ZOH, delay and the
integrator's discretization included, evaluated on ``z = exp(j w T)``) meets
the target with at least ``min_gain_margin_db`` of gain margin, capped by ``max_bandwidth_hz`` and a quarter of the sample rate.

Friction feed-forward (Coulomb per direction and viscous, in the drive's
command units), from the reference velocity ``r``::

    u_ff = B r + coulomb_pos * s(r)  for r >= 0,   B r - coulomb_neg * s(-r)  for r < 0
    s(r) = min(1, r / band)     (fades to 0 at standstill; band 0: a step)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from servobench.errors import UsageError

#: Bisection steps of the crossover search.
_BISECTION_STEPS = 60
#: Points of the frequency grid used to find the margins.
_GRID_POINTS = 4000


@dataclass(frozen=True)
class PIDesign:
    """A velocity-loop PI and its margins.

    Attributes
    ----------
    kp : float
        Proportional gain [command units per (velocity units/s)].
    ki : float
        Integral gain ``Kp/Ti`` [command units per (velocity units/s) per s].
    ti_s : float
        Integral time [s].
    sample_time_s : float
        Loop period ``T`` [s].
    delay_cycles : float
        Delay beyond the zero-order hold [cycles].
    crossover_hz : float
        Gain crossover [Hz].
    phase_margin_deg : float
        Discrete-time phase margin [deg].
    gain_margin_db : float
        Discrete-time gain margin [dB] (inf if the phase never reaches -180 deg).
    limited_by : str
        What set the crossover: ``"phase margin"``, ``"gain margin"``,
        ``"max_bandwidth_hz"`` or ``"sample rate"``.
    """

    kp: float
    ki: float
    ti_s: float
    sample_time_s: float
    delay_cycles: float
    crossover_hz: float
    phase_margin_deg: float
    gain_margin_db: float
    limited_by: str

    def as_dict(self) -> dict[str, float | str]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class FrictionFeedForward:
    """Friction feed-forward parameters in the drive's units.

    Attributes
    ----------
    coulomb_pos : float
        Added for positive reference velocity [command units] (magnitude >= 0).
    coulomb_neg : float
        Subtracted for negative reference velocity [command units] (magnitude >= 0).
    viscous : float
        ``B``, times the reference velocity [command units per (velocity units/s)].
    sign_band : float
        Reference speed over which the Coulomb term ramps in [velocity units/s]; 0 = a step.
    """

    coulomb_pos: float
    coulomb_neg: float
    viscous: float
    sign_band: float = 0.0

    def __post_init__(self) -> None:
        if min(self.coulomb_pos, self.coulomb_neg, self.viscous, self.sign_band) < 0:
            raise UsageError("feed-forward parameters must be >= 0")

    def __call__(self, v_ref: np.ndarray) -> np.ndarray:
        """Feed-forward command [command units] for reference velocities ``v_ref``, shape (n,)."""
        r = np.asarray(v_ref, dtype=float)
        s = np.clip(r / self.sign_band, -1.0, 1.0) if self.sign_band > 0 else np.sign(r)
        coulomb = np.where(s >= 0, self.coulomb_pos * s, self.coulomb_neg * s)
        return self.viscous * r + coulomb

    def as_dict(self) -> dict[str, float]:
        return dict(self.__dict__)


def friction_feed_forward(
    B: float, coulomb_pos: float, coulomb_neg: float, sign_band: float = 0.0
) -> FrictionFeedForward:
    """Feed-forward from identified viscous ``B`` and Coulomb levels (negative levels clip to 0)."""
    return FrictionFeedForward(max(coulomb_pos, 0.0), max(coulomb_neg, 0.0), max(B, 0.0), sign_band)


def loop_response(
    M: float, B: float, kp: float, ki: float, T: float, delay_cycles: float, w: np.ndarray
) -> np.ndarray:
    """Open-loop frequency response ``L(exp(j w T))`` at angular frequencies ``w`` [rad/s]."""
    z = np.exp(1j * w * T)
    a = math.exp(-B * T / M)
    plant = (1.0 - a) / (B * (z - a))
    pi = kp + ki * T * z / (z - 1.0)
    return pi * plant * z ** (-delay_cycles)


def margins(
    M: float, B: float, kp: float, ki: float, T: float, delay_cycles: float
) -> tuple[float, float, float]:
    """Crossover [rad/s], phase margin [deg], gain margin [dB] of the discrete loop."""
    w = np.logspace(math.log10(1e-3 / T), math.log10(math.pi / T * 0.999), _GRID_POINTS)
    L = loop_response(M, B, kp, ki, T, delay_cycles, w)
    mag = np.abs(L)
    phase = np.unwrap(np.angle(L))
    below = np.flatnonzero(mag < 1.0)
    if below.size == 0:
        return math.nan, -math.inf, -math.inf
    i = int(below[0])
    wc = float(w[i])
    pm = math.degrees(math.pi + phase[i])
    cross = np.flatnonzero(phase <= -math.pi)
    gm = -20.0 * math.log10(mag[int(cross[0])]) if cross.size else math.inf
    return wc, pm, gm


def _gains_at(M: float, B: float, T: float, d: float, wc: float, ratio: float) -> tuple[float, float]:
    """Kp, Ki that put the crossover at ``wc`` with ``Ti = min(ratio / wc, M / B)``."""
    ti = min(ratio / wc, M / B)
    unit = loop_response(M, B, 1.0, 1.0 / ti, T, d, np.array([wc]))[0]
    kp = 1.0 / abs(unit)
    return float(kp), float(kp / ti)


def design_pi(
    M: float,
    B: float,
    fs_hz: float,
    *,
    phase_margin_deg: float = 60.0,
    delay_cycles: float = 1.0,
    pi_zero_ratio: float = 4.0,
    max_bandwidth_hz: float | None = None,
    min_gain_margin_db: float = 6.0,
) -> PIDesign:
    """The fastest PI meeting the phase margin on ``1/(M s + B)`` at ``fs_hz`` with the delay.

    Parameters
    ----------
    M, B : float
        Identified inertia [command units s^2/unit] and viscous coefficient [command units s/unit], > 0.
    fs_hz : float
        Loop sample rate [Hz].
    phase_margin_deg : float
        Target phase margin [deg].
    delay_cycles : float
        Delay beyond the zero-order hold [cycles].
    pi_zero_ratio : float
        ``wc * Ti`` (unless the plant pole is faster, see the module docstring).
    max_bandwidth_hz : float, optional
        Crossover cap [Hz].
    min_gain_margin_db : float
        Smallest acceptable gain margin [dB].

    Raises
    ------
    UsageError
        Non-positive plant or rate, or margins the PI cannot reach.
    """
    if not (M > 0 and B > 0 and fs_hz > 0):
        raise UsageError(f"PI design needs M > 0, B > 0 and fs > 0 (got M={M}, B={B}, fs={fs_hz})")
    T = 1.0 / fs_hz
    w_hi = 0.25 * math.pi / T
    limited_by = "sample rate"
    if max_bandwidth_hz is not None and 2 * math.pi * max_bandwidth_hz < w_hi:
        w_hi, limited_by = 2 * math.pi * max_bandwidth_hz, "max_bandwidth_hz"
    w_lo = min(1e-3 / T, w_hi / 1e3)

    def meets(wc: float) -> bool:
        kp, ki = _gains_at(M, B, T, delay_cycles, wc, pi_zero_ratio)
        _, pm, gm = margins(M, B, kp, ki, T, delay_cycles)
        return pm >= phase_margin_deg and gm >= min_gain_margin_db

    if not meets(w_lo):
        raise UsageError(
            f"no PI reaches {phase_margin_deg:g} deg of phase margin and {min_gain_margin_db:g} dB "
            "of gain margin on this plant; lower [design] phase_margin_deg"
        )
    if meets(w_hi):
        wc = w_hi
    else:
        limited_by = "phase margin"
        lo, hi = math.log(w_lo), math.log(w_hi)
        for _ in range(_BISECTION_STEPS):
            mid = 0.5 * (lo + hi)
            if meets(math.exp(mid)):
                lo = mid
            else:
                hi = mid
        wc = math.exp(lo)
    kp, ki = _gains_at(M, B, T, delay_cycles, wc, pi_zero_ratio)
    w_cross, pm, gm = margins(M, B, kp, ki, T, delay_cycles)
    if gm < min_gain_margin_db + 0.01 and limited_by == "phase margin" and pm > phase_margin_deg + 0.5:
        limited_by = "gain margin"
    return PIDesign(
        kp=kp,
        ki=ki,
        ti_s=kp / ki,
        sample_time_s=T,
        delay_cycles=delay_cycles,
        crossover_hz=float(w_cross / (2 * math.pi)),
        phase_margin_deg=float(pm),
        gain_margin_db=float(gm),
        limited_by=limited_by,
    )
