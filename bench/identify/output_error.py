"""Output-error refinement and the Cramér-Rao bound, on the exact stick-slip simulator.

The parameters ``(M, B, coulomb_pos, coulomb_neg)`` minimise the squared
difference between the measured velocity and the velocity the model
simulates from the logged command. With white velocity noise this is the
maximum-likelihood estimate; it is unbiased at every amplitude, including
where the axis sticks. Periodic SIDBE runs are first averaged over their
steady-state periods (a sufficient statistic for white noise), so each
evaluation simulates one period per run, whatever the log length.

The covariance of the estimate is the sandwich ``(J^T J)^-1 S (J^T J)^-1`` with
``J`` the sensitivity of the simulated velocity to the parameters and ``S`` the
long-run covariance of the residual's scores
(:func:`~servobench.bench.identify.covariance.hac_covariance`, lags within each
chunk): with white noise it is ``sigma^2 (J^T J)^-1``, which at the true
parameters with the true noise is the Cramér-Rao bound; with coloured noise,
rounding tied to the signal or an effect the model lacks it still covers the
error, where ``sigma^2 (J^T J)^-1`` would state it several times too small.
Whether the residual is white is tested (:attr:`OutputErrorFit.colour`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from servobench.bench.identify.covariance import ResidualColour, hac_covariance, residual_colour
from servobench.bench.identify.derivative import DerivedMotion, differentiate_position
from servobench.bench.identify.simulation import simulate_steady_period, simulate_velocity
from servobench.bench.model.servo import DELAY_KEY, STD_KEYS, ServoModel
from servobench.errors import IdentificationError
from servobench.sim_backend.physics.coulomb import PlantState, simulate_coulomb

#: Largest number of raw samples used by the refinement of a non-periodic log.
MAX_RAW_SAMPLES = 60_000
#: Relative finite-difference step of the sensitivities.
DIFF_STEP = 1e-6
#: Most cost evaluations of one refinement.
MAX_NFEV = 40
#: Free Coulomb levels start at least this fraction of the rms command above zero.
FRICTION_FLOOR = 1e-3
#: How far log M and log B may move from their start (e^20: eight decades either way).
LOG_REACH = 20.0
#: Restart level (fraction of the rms command) when a search ends on the zero bound.
RESTART_FRACTION = 0.01


@dataclass(frozen=True)
class Chunk:
    """A piece of data the model must reproduce.

    Attributes
    ----------
    u : ndarray, shape (n,)
        Command [command units].
    v : ndarray, shape (n,)
        Measured velocity [units/s] (for ``periodic`` chunks: the average period).
    dt_s : float or ndarray
        Sample interval [s] (per interval for irregular sampling).
    v0 : float
        Initial velocity [units/s] (ignored for periodic chunks).
    periodic : bool
        ``u`` is one period of a periodic command and ``v`` its steady state.
    skip : int
        Leading samples left out of the comparison (initial transient of unknown state).
    weight : float or ndarray
        Number of raw samples each compared sample stands for (periods averaged),
        one value or one per compared sample.
    derive : DerivedMotion or None
        Set when ``v`` was derived from position: the simulated position then goes
        through the same filter and derivative, so both sides are filtered alike.
    x0 : float
        Initial position [units] (derived chunks).
    act_offset_s : ndarray or None
        Each command's own shift of its action instant [s] on top of the model's delay
        (:attr:`~servobench.bench.identify.dataset.Segment.act_offset_s`).
    """

    u: np.ndarray
    v: np.ndarray
    dt_s: float | np.ndarray
    v0: float = 0.0
    periodic: bool = False
    skip: int = 0
    weight: float | np.ndarray = 1.0
    derive: DerivedMotion | None = None
    x0: float = 0.0
    act_offset_s: np.ndarray | None = None


def simulate_chunk(model: ServoModel, chunk: Chunk) -> np.ndarray:
    """Simulated velocity of ``chunk`` (compared samples only)."""
    if chunk.periodic:
        v = simulate_steady_period(model, chunk.u, float(chunk.dt_s))
    elif chunk.derive is not None:
        dt = float(np.mean(chunk.dt_s))
        _, x, _ = simulate_coulomb(
            chunk.u, dt, model.to_plant_params(), PlantState(chunk.v0, chunk.x0)
        )
        d = chunk.derive
        v = differentiate_position(x, 1.0 / dt, d.cutoff_hz, d.method).v
    else:
        v = simulate_velocity(model, chunk.u, chunk.dt_s, chunk.v0, chunk.act_offset_s)
    end = len(v) - chunk.skip if chunk.derive is not None else len(v)
    return v[chunk.skip : end]


def measured_chunk(chunk: Chunk) -> np.ndarray:
    """The measured samples ``simulate_chunk`` is compared with."""
    end = len(chunk.v) - chunk.skip if chunk.derive is not None else len(chunk.v)
    return chunk.v[chunk.skip : end]


def _model(p: np.ndarray, base: ServoModel, delay_unit_s: float = 1.0, min_delay_s: float = 0.0) -> ServoModel:
    """The model of parameter vector ``p``: ``(log M, log B, coulomb_pos, coulomb_neg)`` and, as a
    fifth entry, ``1 + (delay - min_delay_s) / delay_unit_s`` (else the base model's delay):
    offset by one, so a relative finite-difference step stays a step of about DIFF_STEP sample
    at the lowest delay allowed."""
    delay = (max(float(p[4]) - 1.0, 0.0) * delay_unit_s + min_delay_s if len(p) > 4
             else base.delay_s)  # fmt: skip
    return ServoModel(
        math.exp(p[0]), math.exp(p[1]), max(float(p[2]), 0.0), max(float(p[3]), 0.0), base.resonance,
        delay,
    )


@dataclass(frozen=True)
class OutputErrorFit:
    """Refined model, 1-sigma stds, residual noise sigma [units/s] of a raw sample, evaluations,
    cost, and the whiteness of the residual (None without one to test)."""

    model: ServoModel
    std: dict[str, float]
    sigma: float
    nfev: int
    cost: float = math.nan
    colour: ResidualColour | None = None


def refine(
    model0: ServoModel,
    chunks: Sequence[Chunk],
    free: Sequence[bool] = (True,) * 4,
    friction_scale: float | None = None,
    *,
    free_delay: bool = False,
    min_delay_s: float = 0.0,
) -> OutputErrorFit:
    """Minimise the simulation error over ``(log M, log B, coulomb_pos, coulomb_neg)``, and the
    drive's action delay ``delay_s`` (from ``model0.delay_s``, >= ``min_delay_s``) with ``free_delay``.

    ``free`` fixes parameters the data cannot see (e.g. friction in a direction
    never travelled) at their starting value. Zero friction is a kink of the
    cost (no sticking at all), where a bounded search can stall: free Coulomb
    levels start at least ``FRICTION_FLOOR * friction_scale`` (default scale:
    the rms command) above it, and a search that ends on the bound is
    restarted from ``RESTART_FRACTION * friction_scale``; the lower cost wins.
    """
    if friction_scale is None:
        friction_scale = math.sqrt(float(np.mean(np.concatenate([c.u for c in chunks]) ** 2)))
    floor = FRICTION_FLOOR * friction_scale
    fp = max(model0.coulomb_pos, floor) if free[2] else model0.coulomb_pos
    fn = max(model0.coulomb_neg, floor) if free[3] else model0.coulomb_neg
    best = _refine_once(replace(model0, coulomb_pos=fp, coulomb_neg=fn), chunks, free, free_delay,
                        min_delay_s)  # fmt: skip
    on_bound = (free[2] and best.model.coulomb_pos <= floor * 1e-3) or (
        free[3] and best.model.coulomb_neg <= floor * 1e-3
    )
    if on_bound:
        level = RESTART_FRACTION * friction_scale
        again = _refine_once(
            replace(
                best.model,
                coulomb_pos=level if free[2] else best.model.coulomb_pos,
                coulomb_neg=level if free[3] else best.model.coulomb_neg,
            ),
            chunks,
            free,
            free_delay,
            min_delay_s,
        )
        if again.cost < best.cost:
            best = again
    return best


def _refine_once(
    model0: ServoModel, chunks: Sequence[Chunk], free: Sequence[bool], free_delay: bool = False,
    min_delay_s: float = 0.0,
) -> OutputErrorFit:
    from scipy.optimize import least_squares

    free_idx = [i for i in range(4) if free[i]] + ([4] if free_delay else [])
    # the delay in units of the mean sample interval: a step of DIFF_STEP is then ~1e-6 sample
    unit = float(np.mean([np.mean(c.dt_s) for c in chunks])) if chunks else 1.0
    p0 = np.array([math.log(model0.M), math.log(model0.B), model0.coulomb_pos, model0.coulomb_neg,
                   1.0 + max(model0.delay_s - min_delay_s, 0.0) / unit])  # fmt: skip
    weights = [np.sqrt(c.weight) for c in chunks]

    def full(q: np.ndarray) -> np.ndarray:
        p = p0.copy()
        p[free_idx] = q
        return p

    def residual(q: np.ndarray) -> np.ndarray:
        m = _model(full(q), model0, unit, min_delay_s)
        return np.concatenate(
            [
                w * (simulate_chunk(m, c) - measured_chunk(c))
                for c, w in zip(chunks, weights, strict=True)
            ]
        )

    # log M and log B within LOG_REACH of the start: a wild trial step cannot overflow exp()
    lower = np.array([p0[0] - LOG_REACH, p0[1] - LOG_REACH, 0.0, 0.0, 1.0])[free_idx]
    upper = np.array([p0[0] + LOG_REACH, p0[1] + LOG_REACH, np.inf, np.inf, np.inf])[free_idx]
    q0 = np.clip(p0[free_idx], lower, upper)
    step = np.full(len(free_idx), DIFF_STEP)
    try:
        sol = least_squares(
            residual,
            q0,
            bounds=(lower, upper),
            x_scale="jac",
            diff_step=step,
            xtol=1e-8,
            ftol=1e-10,
            gtol=1e-10,
            max_nfev=MAX_NFEV,
        )
    except (ValueError, FloatingPointError) as err:
        raise IdentificationError(f"output-error refinement failed: {err}") from None
    p = full(sol.x)
    model = _model(p, model0, unit, min_delay_s)
    sigma2 = 2.0 * sol.cost / max(1, sol.fun.size - len(free_idx))
    # an averaged chunk's residual has variance sigma^2 / weight; the weighting undoes that
    bounds = np.cumsum([measured_chunk(c).size for c in chunks])
    std = _std_from_jacobian(sol.jac, sol.fun, bounds, p, free_idx, unit)
    colour = residual_colour(sol.fun, bounds) if sol.fun.size > 8 and sigma2 > 0 else None
    return OutputErrorFit(model, std, math.sqrt(sigma2), int(sol.nfev), float(sol.cost), colour)


def _std_from_jacobian(
    jac: np.ndarray, r: np.ndarray, bounds: np.ndarray, p: np.ndarray, free_idx: list[int],
    delay_unit_s: float = 1.0,
) -> dict[str, float]:
    """1-sigma of the natural parameters (HAC sandwich on the residual ``r`` of the chunks
    ending at ``bounds``); ``delay_s`` [s] too where the delay was free."""
    scale = np.array([math.exp(p[0]), math.exp(p[1]), 1.0, 1.0, delay_unit_s])[free_idx]
    Jn = np.asarray(jac) / scale  # d r / d natural parameter
    cov = hac_covariance(Jn, np.asarray(r), bounds)
    sd = np.full(5, np.nan)
    sd[free_idx] = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    out = dict(zip(STD_KEYS, (float(x) for x in sd[:4]), strict=True))
    if 4 in free_idx:
        out[DELAY_KEY] = float(sd[4])
    return out


def sensitivity(model: ServoModel, chunks: Sequence[Chunk]) -> np.ndarray:
    """``d v_sim / d (M, B, coulomb_pos, coulomb_neg)`` by central differences, rows weighted by ``sqrt(weight)``."""
    p = np.array([model.M, model.B, model.coulomb_pos, model.coulomb_neg])
    cols = []
    for i in range(4):
        h = DIFF_STEP * max(abs(p[i]), 1e-3 * max(abs(p[2]), abs(p[3]), 1e-9))
        sims = []
        for sign in (1.0, -1.0):
            q = p.copy()
            q[i] += sign * h
            m = ServoModel(q[0], q[1], max(q[2], 0.0), max(q[3], 0.0), model.resonance, model.delay_s)
            sims.append(np.concatenate([np.sqrt(c.weight) * simulate_chunk(m, c) for c in chunks]))
        cols.append((sims[0] - sims[1]) / (2 * h))
    return np.column_stack(cols)


def cramer_rao(model: ServoModel, chunks: Sequence[Chunk], noise_std: float) -> dict[str, float]:
    """Cramér-Rao bound (1-sigma) of ``M, B, coulomb_pos, coulomb_neg`` for white velocity noise ``noise_std``."""
    J = sensitivity(model, chunks)
    cov = noise_std**2 * np.linalg.inv(J.T @ J)
    return dict(
        zip(STD_KEYS, (float(x) for x in np.sqrt(np.clip(np.diag(cov), 0.0, None))), strict=True)
    )
