"""The served CiA 402 drive's own position loop (cyclic synchronous position, 0x6060 = 8).

At each SYNC the drive computes, from the position and velocity it samples
there, the torque it applies until the next SYNC, as a real drive's loop
does at its cycle rate::

    e   = x_ref - x                                  (0x607A - 0x6064, in plant units)
    tau = kp e + ki sum(e dt) - kd v + tau_offset    (0x60B2), limited to +-tau_max (0x6072)

PID on position with the derivative on the measured velocity (no kick when
the target steps), and the integral frozen while the output saturates (no
wind-up). Gains are in plant units (N m/rad, N m/(rad s), N m s/rad, or per m
on a linear axis), from the ``sim://`` keys ``pos_kp``, ``pos_ki``,
``pos_kd``; by default from the plant (:func:`default_gains`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

#: Closed-loop natural frequency of the default gains [Hz].
DEFAULT_BANDWIDTH_HZ = 2.0
#: Damping ratio of the default gains.
DEFAULT_DAMPING = 0.7
#: Integral corner as a fraction of the natural frequency (default gains).
INTEGRAL_FRACTION = 0.2


@dataclass(frozen=True)
class Gains:
    """PID gains of the position loop, in plant units."""

    kp: float
    ki: float
    kd: float

    def as_dict(self) -> dict[str, float]:
        return {"pos_kp": self.kp, "pos_ki": self.ki, "pos_kd": self.kd}


def default_gains(M: float, B: float, bandwidth_hz: float = DEFAULT_BANDWIDTH_HZ) -> Gains:
    """Gains that place the loop on ``M s^2 + (B + kd) s + kp`` at ``bandwidth_hz``, damping 0.7.

    ``kp = M w^2``, ``kd = max(2 zeta w M - B, 0)`` (the plant's own damping
    counts), ``ki = kp w / 5`` removes the Coulomb offset within a few periods.
    """
    w = 2.0 * math.pi * bandwidth_hz
    kp = M * w * w
    return Gains(kp, kp * w * INTEGRAL_FRACTION, max(2.0 * DEFAULT_DAMPING * w * M - B, 0.0))


def gains_from_keys(keys: Mapping[str, float], M: float, B: float) -> Gains:
    """The ``pos_kp``/``pos_ki``/``pos_kd`` keys given, the defaults for the others."""
    base = default_gains(M, B)
    return Gains(
        keys.get("pos_kp", base.kp), keys.get("pos_ki", base.ki), keys.get("pos_kd", base.kd)
    )


class PositionLoop:
    """The PID loop, stepped once per SYNC with the cycle period ``dt_s``."""

    def __init__(self, gains: Gains) -> None:
        self.gains = gains
        self._integral = 0.0

    def reset(self) -> None:
        """Forget the integral (on entering the mode, and after a stop)."""
        self._integral = 0.0

    def torque(
        self, error: float, velocity: float, offset: float, limit: float, dt_s: float
    ) -> float:
        """The torque for this cycle, limited to ``+-limit``."""
        g = self.gains
        integral = self._integral + error * dt_s
        tau = g.kp * error + g.ki * integral - g.kd * velocity + offset
        if -limit <= tau <= limit:
            self._integral = integral  # integrate only while unsaturated
        return min(max(tau, -limit), limit)
