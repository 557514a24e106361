"""The hold loop: a slow position controller that keeps the axis inside its travel while it is excited.

On an axis with limited travel the excitation ``u_exc`` cannot be applied
alone: binary excitation drifts, and asymmetric Coulomb friction makes the
drift grow every period. The hold loop adds a low-bandwidth position
controller, so the total command is::

    u = u_exc + kp (x_ref - x) + ki integral(x_ref - x) dt - kd v

clamped to ``max_u`` (the integral is frozen while the output saturates
outwards: no wind-up). Its bandwidth lies well below the lowest excited line
(:data:`LINE_OVER_BANDWIDTH`), so at the excited lines the axis moves almost
as it would in open loop, while drift and the slow friction offset are
taken out. The loop runs on the host (any drive in torque mode; the command
computed from the sample of cycle ``k`` acts from cycle ``k + 1``) or, where
the protocol has one, in the drive (:meth:`~servobench.drivers.base.Drive.hold_position`,
without that cycle of delay).

Gains come from the plant ``1/(M s + B)`` seen by position, ``1/(s (M s + B))``:
the characteristic polynomial ``M s^3 + (B + kd) s^2 + kp s + ki`` is placed
at ``(s^2 + 2 zeta w s + w^2) (M s + c)`` with ``w = 2 pi bandwidth_hz``.
``kd`` is only added where the plant's own damping ``B`` is too small
(``B + kd >= 3 M w``), which keeps the third pole ``-c/M`` at or beyond ``-w``.

Units: ``kp`` [command units per position unit], ``ki`` [command units per
position unit and second], ``kd`` [command units per velocity unit].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from servobench.bench.model.servo import ServoModel
from servobench.errors import UsageError
from servobench.sim_backend.physics.coulomb import PlantState, simulate_coulomb

#: Lowest excited line over the hold loop's bandwidth.
LINE_OVER_BANDWIDTH = 5.0
#: Damping ratio of the hold loop's dominant poles.
HOLD_DAMPING = 1.0
#: ``B + kd`` is at least this multiple of ``M w`` (places the third pole at or beyond ``-w``).
DAMPING_OVER_MASS = 3.0
#: Where the loop runs, and the cycles between the sample it uses and the command it sets.
DELAY_CYCLES = {"host": 1, "drive": 0}


@dataclass(frozen=True)
class HoldGains:
    """Gains of the hold loop (see the module docstring for their units).

    Attributes
    ----------
    kp, ki, kd : float
        Proportional, integral and velocity gains, each >= 0.
    bandwidth_hz : float
        Natural frequency the gains were placed at [Hz] (NaN when given by hand).
    """

    kp: float
    ki: float
    kd: float
    bandwidth_hz: float = math.nan

    def __post_init__(self) -> None:
        for name in ("kp", "ki", "kd"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise UsageError(f"hold gain {name} must be a finite number >= 0, got {value!r}")
        if not self.kp > 0:
            raise UsageError("hold gain kp must be > 0")


def fit_hold_gains(
    u_loop: np.ndarray, error: np.ndarray, v: np.ndarray, dt_s: float
) -> HoldGains | None:
    """The gains of a loop ``u_loop = kp e + ki integral(e) dt - kd v`` from its samples.

    For a drive's own loop, whose gains the drive does not state: ``u_loop`` is
    the total command it reports applied less the host's offset [command
    units], ``e = x_ref - x`` [position units], ``v`` [velocity units], all of
    shape ``(n,)``; the integral is taken from the first sample. Least squares
    on the three columns; None when the samples do not show a loop that holds
    (``kp`` not positive, or a singular fit).
    """
    e = np.asarray(error, dtype=float)
    X = np.column_stack((e, np.cumsum(e) * dt_s, -np.asarray(v, dtype=float), np.ones_like(e)))
    scale = np.sqrt(np.mean(X * X, axis=0))
    if not np.all(scale > 0):
        return None
    theta, *_ = np.linalg.lstsq(X / scale, np.asarray(u_loop, dtype=float), rcond=None)
    kp, ki, kd, _ = theta / scale  # the constant takes the integral's start
    if not (math.isfinite(kp) and kp > 0):
        return None
    return HoldGains(float(kp), max(float(ki), 0.0), max(float(kd), 0.0))


def design_hold(M: float, B: float, bandwidth_hz: float, zeta: float = HOLD_DAMPING) -> HoldGains:
    """Gains that place the hold loop on ``1/(s (M s + B))`` at ``bandwidth_hz`` [Hz].

    Parameters
    ----------
    M, B : float
        The plant [command units s^2 / position unit, command units s / position unit].
    bandwidth_hz : float
        Natural frequency of the dominant pole pair [Hz].
    zeta : float
        Damping ratio of that pair, in (0, 1.5].
    """
    if not (M > 0 and B > 0 and bandwidth_hz > 0 and 0 < zeta <= 1.5):
        raise UsageError(
            f"hold design needs M, B, bandwidth > 0 and 0 < zeta <= 1.5 "
            f"(got M={M:g}, B={B:g}, bandwidth={bandwidth_hz:g} Hz, zeta={zeta:g})"
        )
    w = 2.0 * math.pi * bandwidth_hz
    kd = max(DAMPING_OVER_MASS * M * w - B, 0.0)
    c = B + kd - 2.0 * zeta * w * M
    return HoldGains(2.0 * zeta * w * c + M * w * w, c * w * w, kd, float(bandwidth_hz))


@dataclass(frozen=True)
class HoldController:
    """One hold loop as run: gains, where it runs, what it holds, its limit.

    Attributes
    ----------
    gains : HoldGains
    where : {"host", "drive"}
        The host's loop, or the drive's own (CiA 402 cyclic synchronous position).
    x_ref : float
        Position held [position units].
    dt_s : float
        Cycle period [s].
    max_u : float
        Largest ``|u|`` [command units].
    """

    gains: HoldGains
    where: str
    x_ref: float
    dt_s: float
    max_u: float = math.inf

    def __post_init__(self) -> None:
        if self.where not in DELAY_CYCLES:
            raise UsageError(f"hold loop runs on 'host' or 'drive', not {self.where!r}")

    @property
    def delay_cycles(self) -> int:
        return DELAY_CYCLES[self.where]

    def metadata(self) -> dict[str, object]:
        """The ``# key = value`` lines of a closed-loop log (for a drive's own loop, the
        gains the host measured it to have, or designed for it to predict with)."""
        g = self.gains
        out: dict[str, object] = {
            "loop": "closed",
            "hold": self.where,
            "x_ref": self.x_ref,
            "hold_delay_cycles": self.delay_cycles,
            "hold_kp": g.kp,
            "hold_ki": g.ki,
            "hold_kd": g.kd,
            "hold_bandwidth_hz": g.bandwidth_hz,
        }
        if self.where == "drive":
            out["hold_gains"] = (
                "measured from the drive" if math.isnan(g.bandwidth_hz)
                else "the drive's own are not known: the host's design stands in"
            )  # fmt: skip
        return out


class HoldLoop:
    """The host's hold loop, stepped once per cycle (its state: the integral).

    Parameters
    ----------
    controller : HoldController
    """

    def __init__(self, controller: HoldController) -> None:
        self.c = controller
        self.x_ref = controller.x_ref
        self._integral = 0.0

    def reset(self) -> None:
        """Forget the integral (at the start of a run, as the prediction starts)."""
        self._integral = 0.0

    def command(self, u_exc: float, x: float, v: float) -> float:
        """Total command [command units] for excitation ``u_exc`` and the feedback ``x``, ``v``."""
        g, limit = self.c.gains, self.c.max_u
        e = self.x_ref - x
        integral = self._integral + e * self.c.dt_s
        u = u_exc + g.kp * e + g.ki * integral - g.kd * v
        if -limit <= u <= limit or (u > limit) != (e > 0):
            self._integral = integral  # integrate unless saturated outwards
        return min(max(u, -limit), limit)


@dataclass(frozen=True)
class HoldResponse:
    """A simulated hold, arrays of shape ``(n,)``: position, velocity, total command."""

    x: np.ndarray
    v: np.ndarray
    u: np.ndarray

    def excursion(self, x_ref: float = 0.0) -> float:
        """Largest ``|x - x_ref|`` [position units]."""
        return float(np.max(np.abs(self.x - x_ref))) if self.x.size else 0.0


def simulate_hold(
    model: ServoModel, controller: HoldController, u_exc: np.ndarray, v0: float = 0.0
) -> HoldResponse:
    """The noise-free hold of ``model`` excited by ``u_exc`` from ``x_ref`` (exact ZOH, stick-slip).

    The loop sees the sample ``delay_cycles`` before the cycle it commands.
    """
    params = model.to_plant_params()
    loop = HoldLoop(controller)
    dt = controller.dt_s
    state = PlantState(v0, controller.x_ref)
    n = len(u_exc)
    x, v, u = np.empty(n), np.empty(n), np.empty(n)
    seen_x, seen_v = state.x, state.v
    one = np.empty(1)
    for k, uk in enumerate(np.asarray(u_exc, dtype=float).tolist()):
        x[k], v[k] = state.x, state.v
        if controller.delay_cycles == 0:
            seen_x, seen_v = state.x, state.v
        one[0] = u[k] = loop.command(uk, seen_x, seen_v)
        seen_x, seen_v = state.x, state.v
        _, _, state = simulate_coulomb(one, dt, params, state)
    return HoldResponse(x, v, u)
