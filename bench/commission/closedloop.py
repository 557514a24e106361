"""Check the PI and the friction feed-forward in simulation on the identified plant.

The velocity loop runs on the exact stick-slip plant of
:mod:`servobench.sim_backend.physics.plant` built from the identified model (Coulomb friction
per direction, no sensor noise), at the design's sample time, with its delay,
the command clamped to max_u and a clamping anti-windup. A slow reversing
reference (a sinusoid a few times the Coulomb breakaway velocity) makes the
friction matter: each reversal sticks the axis until the loop builds up the
breakaway command, which the feed-forward supplies at once.

Loop, cycle ``k`` (``d`` = delay in whole cycles)::

    e_k = r_k - v_k
    I_k = I_{k-1} + Ki T e_k         (held while the command saturates outwards)
    c_k = Kp e_k + I_k + u_ff(r_{k+d})
    u applied over [t_k, t_k+1) = clip(c_{k-d}, -max_u, max_u)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from servobench.bench.commission.config import CompensationSettings
from servobench.bench.commission.design import FrictionFeedForward, PIDesign
from servobench.sim_backend.physics.plant import Plant, PlantParams

#: Default reference amplitude over the Coulomb breakaway velocity mean(Fc)/B.
AMPLITUDE_OVER_BREAKAWAY = 2.0
#: Largest default reference amplitude [fraction of max_v].
MAX_AMPLITUDE_FRACTION = 0.25
#: Fraction of max_u the default reference may need.
SAFE_COMMAND_FRACTION = 0.5


@dataclass(frozen=True)
class LoopRun:
    """One closed-loop simulation; arrays of shape ``(n,)``.

    Attributes
    ----------
    t_s : ndarray
        Time [s].
    v_ref, v : ndarray
        Reference and plant velocity [velocity units/s].
    u : ndarray
        Command applied [command units].
    rms_error, max_error : float
        RMS and largest ``|v_ref - v|`` [velocity units/s].
    """

    t_s: np.ndarray
    v_ref: np.ndarray
    v: np.ndarray
    u: np.ndarray
    rms_error: float
    max_error: float

    def __post_init__(self) -> None:
        n = self.t_s.shape
        if not (self.v_ref.shape == self.v.shape == self.u.shape == n):
            raise ValueError("LoopRun arrays must share one shape")


@dataclass(frozen=True)
class CompensationCheck:
    """PI alone versus PI plus friction feed-forward on the same reference.

    Attributes
    ----------
    amplitude : float
        Reference amplitude [velocity units/s].
    frequency_hz : float
        Reference frequency [Hz].
    without_ff, with_ff : LoopRun
        The two simulations.
    """

    amplitude: float
    frequency_hz: float
    without_ff: LoopRun
    with_ff: LoopRun

    @property
    def rms_ratio(self) -> float:
        """RMS tracking error with compensation over without (< 1: it helps)."""
        return self.with_ff.rms_error / self.without_ff.rms_error if self.without_ff.rms_error else 1.0

    def as_dict(self) -> dict[str, float]:
        return {
            "reference_amplitude": self.amplitude,
            "reference_frequency_hz": self.frequency_hz,
            "rms_error_without_ff": self.without_ff.rms_error,
            "rms_error_with_ff": self.with_ff.rms_error,
            "max_error_without_ff": self.without_ff.max_error,
            "max_error_with_ff": self.with_ff.max_error,
            "rms_ratio": self.rms_ratio,
        }


def simulate_loop(
    params: PlantParams,
    pi: PIDesign,
    v_ref: np.ndarray,
    max_u: float,
    ff: FrictionFeedForward | None = None,
) -> LoopRun:
    """Run the velocity loop on ``params`` from rest, tracking ``v_ref`` sampled at ``pi.sample_time_s``."""
    T = pi.sample_time_s
    d = max(0, int(round(pi.delay_cycles)))
    r = np.asarray(v_ref, dtype=float)
    n = r.size
    ahead = np.concatenate([r[d:], np.full(d, r[-1] if n else 0.0)])
    u_ff = ff(ahead) if ff is not None else np.zeros(n)
    plant = Plant(
        params.with_changes(
            brk_pos=None, brk_neg=None, noise=0.0, noise_x=0.0, res_x=0.0, res_v=0.0,
        )
    )  # fmt: skip
    v = np.empty(n)
    u = np.empty(n)
    pending = [0.0] * d
    integ = 0.0
    for k in range(n):
        v[k] = plant.state.v
        e = r[k] - v[k]
        trial = integ + pi.ki * T * e
        c = pi.kp * e + trial + u_ff[k]
        saturated = abs(c) > max_u and math.copysign(1.0, c) == math.copysign(1.0, e)
        if not saturated:
            integ = trial
        pending.append(min(max(c, -max_u), max_u))
        u[k] = pending.pop(0)
        plant.step_block(np.array([u[k]]), T)
    err = r - v
    return LoopRun(
        t_s=np.arange(n) * T,
        v_ref=r,
        v=v,
        u=u,
        rms_error=float(np.sqrt(np.mean(err**2))) if n else 0.0,
        max_error=float(np.max(np.abs(err))) if n else 0.0,
    )


def reference_amplitude(
    M: float,
    B: float,
    coulomb_pos: float,
    coulomb_neg: float,
    max_u: float,
    max_v: float,
    settings: CompensationSettings,
) -> float:
    """The reference amplitude [velocity units/s] of the compensation check.

    The configured one, else twice the Coulomb breakaway velocity
    ``mean(Fc)/B``, at most ``max_v/4`` and at most what half of max_u can
    drive at the reference frequency (``(M w + B) A + max(Fc) <= max_u/2``).
    """
    if settings.ref_amplitude is not None:
        return min(settings.ref_amplitude, max_v)
    coulomb_pos, coulomb_neg = max(coulomb_pos, 0.0), max(coulomb_neg, 0.0)
    breakaway_v = 0.5 * (coulomb_pos + coulomb_neg) / B
    w = 2 * math.pi * settings.ref_frequency_hz
    drivable = (SAFE_COMMAND_FRACTION * max_u - max(coulomb_pos, coulomb_neg)) / (M * w + B)
    cap = min(MAX_AMPLITUDE_FRACTION * max_v, drivable) if drivable > 0 else MAX_AMPLITUDE_FRACTION * max_v
    return min(AMPLITUDE_OVER_BREAKAWAY * breakaway_v, cap) if breakaway_v > 0 else cap


def check_compensation(
    M: float,
    B: float,
    coulomb_pos: float,
    coulomb_neg: float,
    pi: PIDesign,
    ff: FrictionFeedForward,
    max_u: float,
    max_v: float,
    settings: CompensationSettings,
) -> CompensationCheck:
    """Track a slow reversing sinusoid on the identified plant with and without ``ff``."""
    params = PlantParams(M=M, B=B, coulomb_pos=max(coulomb_pos, 0.0), coulomb_neg=max(coulomb_neg, 0.0))
    amplitude = reference_amplitude(M, B, coulomb_pos, coulomb_neg, max_u, max_v, settings)
    f = settings.ref_frequency_hz
    n = int(round(settings.periods / f / pi.sample_time_s))
    t = np.arange(n) * pi.sample_time_s
    r = amplitude * np.sin(2 * math.pi * f * t)
    return CompensationCheck(
        amplitude=amplitude,
        frequency_hz=f,
        without_ff=simulate_loop(params, pi, r, max_u, None),
        with_ff=simulate_loop(params, pi, r, max_u, ff),
    )
