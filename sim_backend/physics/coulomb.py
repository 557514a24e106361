"""The DC servo with friction, simulated exactly under zero-order hold.

Model (SI-like, command units ``u``)::

    M dv/dt + B v = u(t) - F_f(v, u)

    F_f =  coulomb_pos                  v > 0
    F_f = -coulomb_neg                  v < 0
    F_f =  u   (stuck, v stays 0)       v = 0 and -brk_neg <= u <= brk_pos

``coulomb_pos``, ``coulomb_neg`` are the Coulomb levels (magnitudes >= 0) for
positive and negative motion (``sim://`` keys ``fc_pos``, ``fc_neg``, see
:mod:`servobench.sim_backend.simurl`), ``brk_pos`` >= ``coulomb_pos`` and
``brk_neg`` >= ``coulomb_neg`` the breakaway (static) levels. With ``u`` held constant over a sample
interval the solution is an exponential towards ``(u - F_f)/B`` in each
regime; the integrator finds the zero crossing inside the interval
analytically and then either sticks (command within breakaway) or continues
in the other regime. There is no switching-function smoothing, so a body at
rest stays exactly at rest and velocity never chatters around zero.

Sampling: ``v[k]`` and ``x[k]`` are taken at ``t_k``, before ``u[k]`` acts on
``[t_k, t_k + dt)``.

This module is the bottom of the physics: it imports no other part of it, so
the plant with effects (:mod:`servobench.sim_backend.physics.rich_plant`) and the
simulated servo (:mod:`servobench.sim_backend.physics.plant`) both build on it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from servobench.errors import UsageError


@dataclass(frozen=True)
class PlantParams:
    """Physical parameters of the simulated servo.

    Attributes
    ----------
    M : float
        Inertia/mass [command units * s^2 / position unit]; > 0.
    B : float
        Viscous coefficient [command units * s / position unit]; > 0. Pole -B/M [1/s], DC gain 1/B.
    coulomb_pos, coulomb_neg : float
        Coulomb friction magnitude in positive / negative motion [command units]
        (``sim://`` keys ``fc_pos``, ``fc_neg``).
    brk_pos, brk_neg : float or None
        Breakaway (static) friction magnitude; ``None`` means equal to the Coulomb level.
    noise : float
        Standard deviation of white velocity-sensor noise [velocity units].
    noise_x : float
        Standard deviation of white position-sensor noise [position units].
    res_x : float
        Encoder resolution [position units per count]; 0 disables quantization.
    res_v : float
        Velocity resolution [velocity units per LSB]; 0 disables quantization.
    seed : int or None
        Seed of the sensor-noise generator.
    effects : Mapping[str, Mapping[str, float]]
        Extra physical effects by name (see :mod:`servobench.sim_backend.physics.effects`).
    """

    M: float = 0.1
    B: float = 1.0
    coulomb_pos: float = 0.5
    coulomb_neg: float = 0.4
    brk_pos: float | None = None
    brk_neg: float | None = None
    noise: float = 0.0
    noise_x: float = 0.0
    res_x: float = 0.0
    res_v: float = 0.0
    seed: int | None = None
    effects: Mapping[str, Mapping[str, float]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("M", "B"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise UsageError(f"plant {name} must be a finite number > 0, got {value!r}")
        for name in ("coulomb_pos", "coulomb_neg", "noise", "noise_x", "res_x", "res_v"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise UsageError(f"plant {name} must be a finite number >= 0, got {value!r}")
        if self.breakaway_pos < self.coulomb_pos or self.breakaway_neg < self.coulomb_neg:
            raise UsageError("breakaway friction must be >= the Coulomb level")

    @property
    def breakaway_pos(self) -> float:
        return self.coulomb_pos if self.brk_pos is None else self.brk_pos

    @property
    def breakaway_neg(self) -> float:
        return self.coulomb_neg if self.brk_neg is None else self.brk_neg

    def with_changes(self, **changes: object) -> PlantParams:
        return replace(self, **changes)


@dataclass
class PlantState:
    """Integrator state: true velocity [units/s] and position [units]."""

    v: float = 0.0
    x: float = 0.0


def simulate_coulomb(
    u: np.ndarray,
    dt_s: float,
    params: PlantParams,
    state: PlantState | None = None,
) -> tuple[np.ndarray, np.ndarray, PlantState]:
    """Exact ZOH simulation of the linear block with Coulomb/breakaway friction.

    Parameters
    ----------
    u : ndarray, shape (n,)
        Command held over each interval [command units].
    dt_s : float
        Sample interval [s].
    params : PlantParams
        Plant; its ``effects`` and sensor terms are ignored here.
    state : PlantState, optional
        Initial state (rest at the origin by default); not modified.

    Returns
    -------
    v, x : ndarray, shape (n,)
        True velocity and position at the start of each interval.
    state : PlantState
        State at the end of the last interval.
    """
    if not dt_s > 0:
        raise UsageError("sample interval must be > 0 s")
    st = PlantState() if state is None else PlantState(state.v, state.x)
    M, B = params.M, params.B
    fcp, fcn = params.coulomb_pos, params.coulomb_neg
    bkp, bkn = params.breakaway_pos, params.breakaway_neg
    tau = M / B
    a = math.exp(-dt_s / tau)
    g = tau * (1.0 - a)
    exp, log = math.exp, math.log
    v, x = st.v, st.x
    vs: list[float] = []
    xs: list[float] = []
    push_v, push_x = vs.append, xs.append
    for uk in np.asarray(u, dtype=float).tolist():
        push_v(v)
        push_x(x)
        if v > 0.0 or (v == 0.0 and uk > bkp):
            f, forward = fcp, True
        elif v < 0.0 or uk < -bkn:
            f, forward = -fcn, False
        else:
            continue  # stuck for the whole interval
        vinf = (uk - f) / B
        vn = vinf + (v - vinf) * a
        if (vn > 0.0) == forward and vn != 0.0:
            x += vinf * dt_s + (v - vinf) * g
            v = vn
            continue
        # The velocity reaches zero inside the interval, at t_c.
        tc = tau * log((v - vinf) / -vinf)
        x += vinf * tc + (v - vinf) * tau * (1.0 - exp(-tc / tau))
        rest = dt_s - tc
        if -bkn <= uk <= bkp:
            v = 0.0
            continue
        f2 = fcp if uk > bkp else -fcn
        vinf2 = (uk - f2) / B
        e2 = exp(-rest / tau)
        x += vinf2 * rest - vinf2 * tau * (1.0 - e2)
        v = vinf2 * (1.0 - e2)
    return np.array(vs), np.array(xs), PlantState(v, x)


def simulate_coulomb_steps(
    u: np.ndarray,
    dt_s: np.ndarray,
    params: PlantParams,
    state: PlantState | None = None,
) -> tuple[np.ndarray, np.ndarray, PlantState]:
    """:func:`simulate_coulomb` with its own interval after each sample.

    ``u`` has shape ``(n,)`` and ``dt_s`` shape ``(n - 1,)`` [s] (>= 0; the
    last command is held for no time): the grid of a delayed command
    (:func:`servobench.bench.identify.delay.merged_grid`), or any irregular one.
    Same piecewise-exponential solution, velocity and position at each grid
    instant, and the state at the last one.
    """
    st = PlantState() if state is None else PlantState(state.v, state.x)
    M, B = params.M, params.B
    fcp, fcn = params.coulomb_pos, params.coulomb_neg
    bkp, bkn = params.breakaway_pos, params.breakaway_neg
    tau = M / B
    exp, log = math.exp, math.log
    v, x = st.v, st.x
    vs: list[float] = []
    xs: list[float] = []
    push_v, push_x = vs.append, xs.append
    steps = np.asarray(dt_s, dtype=float).tolist() + [0.0]
    for uk, dt in zip(np.asarray(u, dtype=float).tolist(), steps, strict=True):
        push_v(v)
        push_x(x)
        if dt <= 0.0:
            continue
        if v > 0.0 or (v == 0.0 and uk > bkp):
            f, forward = fcp, True
        elif v < 0.0 or uk < -bkn:
            f, forward = -fcn, False
        else:
            continue  # stuck for the whole interval
        vinf = (uk - f) / B
        a = exp(-dt / tau)
        vn = vinf + (v - vinf) * a
        if (vn > 0.0) == forward and vn != 0.0:
            x += vinf * dt + (v - vinf) * tau * (1.0 - a)
            v = vn
            continue
        tc = tau * log((v - vinf) / -vinf)
        x += vinf * tc + (v - vinf) * tau * (1.0 - exp(-tc / tau))
        rest = dt - tc
        if -bkn <= uk <= bkp:
            v = 0.0
            continue
        f2 = fcp if uk > bkp else -fcn
        vinf2 = (uk - f2) / B
        e2 = exp(-rest / tau)
        x += vinf2 * rest - vinf2 * tau * (1.0 - e2)
        v = vinf2 * (1.0 - e2)
    return np.array(vs), np.array(xs), PlantState(v, x)
