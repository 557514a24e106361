"""Simulate an identified model on logged commands.

Thin layer over the exact stick-slip integrator
:func:`servobench.sim_backend.physics.coulomb.simulate_coulomb`, adding what identification
needs: irregular sample intervals (an exact per-interval integrator, same
equations), the optional series resonance, a warm start, and the periodic
steady state of a periodic command (long periodic logs are then verified
by simulating a few periods and tiling, which is exact once the transient
has died out -- the plant with Coulomb friction is contractive).
"""

from __future__ import annotations

import math

import numpy as np

from servobench.bench.identify.delay import merged_grid
from servobench.bench.model.servo import ServoModel
from servobench.sim_backend.physics.coulomb import PlantParams, PlantState, simulate_coulomb

#: Time constants of pre-roll that make the periodic steady state exact to ~3e-7.
PREROLL_TIME_CONSTANTS = 15.0


def simulate_velocity(
    model: ServoModel,
    u: np.ndarray,
    dt_s: float | np.ndarray,
    v0: float = 0.0,
    offsets_s: np.ndarray | None = None,
) -> np.ndarray:
    """Noise-free velocity [units/s] at each sample, ``u`` held per interval.

    Parameters
    ----------
    model : ServoModel
    u : ndarray, shape (n,)
        Command [command units].
    dt_s : float or ndarray of shape (n - 1,)
        Sample interval [s], one value or one per interval.
    v0 : float
        Velocity at the first sample [units/s].
    offsets_s : ndarray of shape (n,), optional
        Each command's own shift [s] of its action instant on top of the model's delay
        (:attr:`Segment.act_offset_s <servobench.bench.identify.dataset.Segment.act_offset_s>`).
    """
    u = np.asarray(u, dtype=float)
    params = model.to_plant_params()
    if model.delay_s != 0 or offsets_s is not None:
        v = simulate_delayed(u, dt_s, params, model.delay_s, v0, offsets_s=offsets_s)
        if model.resonance is not None:
            v = model.resonance.filter_velocity(v, float(np.mean(dt_s)))
        return v
    if np.ndim(dt_s) == 0:
        dt = float(dt_s)
        v, _, _ = simulate_coulomb(u, dt, params, PlantState(v0, 0.0))
    else:
        dts = np.asarray(dt_s, dtype=float)
        dt = float(np.mean(dts)) if dts.size else 1.0
        v = simulate_variable_dt(u, dts, params, v0)
    if model.resonance is not None:
        v = model.resonance.filter_velocity(v, dt)
    return v


def simulate_delayed(
    u: np.ndarray,
    dt_s: float | np.ndarray,
    params: PlantParams,
    delay_s: float,
    v0: float = 0.0,
    u_before: float = 0.0,
    offsets_s: np.ndarray | None = None,
) -> np.ndarray:
    """Exact stick-slip velocity at the sample instants when ``u[k]`` acts from ``t_k + delay_s``
    (``+ offsets_s[k]`` where given).

    Simulated on the grid of the sample and switch instants
    (:func:`~servobench.bench.identify.delay.merged_grid`) and taken back at the
    samples; ``u_before`` [command units] is in force until ``u[0]`` acts.
    """
    u_m, dt_m, rows = merged_grid(u, dt_s, delay_s, u_before, offsets_s)
    if u_m.size == 0:
        return u_m
    return simulate_variable_dt(u_m, dt_m, params, v0)[rows]


def simulate_variable_dt(
    u: np.ndarray, dt_s: np.ndarray, params: PlantParams, v0: float = 0.0
) -> np.ndarray:
    """Exact stick-slip velocity with a different interval ``dt_s[k]`` after each sample.

    The same piecewise-exponential solution as
    :func:`~servobench.sim_backend.physics.coulomb.simulate_coulomb`, with ``exp(-dt_k/tau)`` per
    step: :func:`simulate_variable_dt_reference`'s loop compiled
    (:func:`~servobench.sim_backend.physics.kernels.variable_dt_velocity`), equal to it bit for bit
    (``tests/test_compiled_plant.py``). The drive grid's searches run it thousands of times a log.
    """
    from servobench.sim_backend.physics.kernels import variable_dt_velocity

    return _variable_dt(variable_dt_velocity, u, dt_s, params, v0)


def simulate_variable_dt_reference(
    u: np.ndarray, dt_s: np.ndarray, params: PlantParams, v0: float = 0.0
) -> np.ndarray:
    """:func:`simulate_variable_dt` in Python: the compiled loop's own source run by the
    interpreter (``py_func``), the reference it is held to. (It equalled the Python loop it replaced
    bit for bit on 300 random plants and commands.)"""
    from servobench.sim_backend.physics.kernels import variable_dt_velocity

    return _variable_dt(variable_dt_velocity.py_func, u, dt_s, params, v0)


def _variable_dt(loop, u: np.ndarray, dt_s: np.ndarray, params: PlantParams, v0: float) -> np.ndarray:
    """``loop`` (:func:`~servobench.sim_backend.physics.kernels.variable_dt_velocity`, compiled or
    not) on ``u`` and the intervals ``dt_s`` [s] after each sample, from ``v0``."""
    u_a = np.ascontiguousarray(u, dtype=float)
    dts = np.ascontiguousarray(dt_s, dtype=float)
    if dts.size < max(u_a.size - 1, 0):
        raise ValueError(f"{u_a.size} commands need {u_a.size - 1} intervals, got {dts.size}")
    out = np.empty(u_a.size)
    loop(u_a, dts, float(params.M), float(params.B), float(params.coulomb_pos), float(params.coulomb_neg),
         float(params.breakaway_pos), float(params.breakaway_neg), float(v0), out)  # fmt: skip
    return out


def preroll_samples(model: ServoModel, dt_s: float, period: int) -> int:
    """Samples to simulate before a period so its state is the periodic steady state."""
    need = int(math.ceil(PREROLL_TIME_CONSTANTS * model.time_constant_s / dt_s))
    return max(need, 1) if period else 0


def simulate_steady_period(model: ServoModel, u_period: np.ndarray, dt_s: float) -> np.ndarray:
    """Velocity over one period of a periodic command, in periodic steady state.

    The command is applied from rest for :func:`preroll_samples` samples
    (whole periods and a tail) before the returned period.
    """
    u_period = np.asarray(u_period, dtype=float)
    n = len(u_period)
    pre = preroll_samples(model, dt_s, n)
    reps = int(math.ceil(pre / n))
    lead = np.tile(u_period, reps)[-pre:] if pre else u_period[:0]
    v = simulate_velocity(model, np.concatenate((lead, u_period)), dt_s)
    return v[len(lead) :]


def simulate_run(
    model: ServoModel,
    u: np.ndarray,
    dt_s: float | np.ndarray,
    v0: float = 0.0,
    period: int = 0,
    offsets_s: np.ndarray | None = None,
) -> np.ndarray:
    """Velocity over a whole run; with ``period`` (samples) long periodic runs are tiled
    (never with per-row action ``offsets_s``, which make a run aperiodic).

    For a periodic command, periods after the transient equal the steady-state
    period; the run is simulated for its first periods until two consecutive
    periods agree, and the rest is tiled from the last of them. Falls back to
    the full simulation when the command is not periodic or does not settle.
    """
    u = np.asarray(u, dtype=float)
    n = len(u)
    if offsets_s is not None:
        return simulate_velocity(model, u, dt_s, v0, offsets_s)
    if period <= 0 or np.ndim(dt_s) != 0 or model.resonance is not None or n < 6 * period:
        return simulate_velocity(model, u, dt_s, v0)
    whole = n // period
    tail = n - whole * period
    if not (
        np.array_equal(u[: (whole - 1) * period], u[period : whole * period])
        and np.array_equal(u[whole * period :], u[:tail])
    ):
        return simulate_velocity(model, u, dt_s, v0)
    settle = 1 + int(math.ceil(preroll_samples(model, float(dt_s), period) / period))
    head = min(whole, settle + 2)
    v_head = simulate_velocity(model, u[: head * period], dt_s, v0)
    last, before = v_head[(head - 1) * period :], v_head[(head - 2) * period : (head - 1) * period]
    scale = max(float(np.max(np.abs(last))), 1e-300)
    if float(np.max(np.abs(last - before))) > 1e-9 * scale:
        return simulate_velocity(model, u, dt_s, v0)
    reps = whole - head
    return np.concatenate((v_head, np.tile(last, reps), last[:tail]))
