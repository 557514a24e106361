"""The pair regression on irregular intervals: its analytic Jacobian, and the fit it drives.

The Jacobian is held against scipy's central differences of the same residual
(weighted and not, inside and at the bound that stops a diverged step), and
the fit recovers an exact plant from jittered intervals, from a start 20 %
off. The fit's variable projection reaches the minimum scipy's
Levenberg-Marquardt finds on all four unknowns (noisy and weighted pairs, a
direction without motion), and where the command does not drive the
velocity it returns the bounded problem's least sum, below what LM stalls at.
"""

import math

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.optimize._numdiff import approx_derivative

from servobench.bench.identify.regression import (
    DIVERGED_LOG,
    IrregularPairs,
    Pairs,
    _projected,
    fit_pairs_irregular,
)

TRUE = (0.01, 1.0, 0.5, 0.4)  # M, B, coulomb_pos, coulomb_neg


def _pairs(seed: int, noise: float = 0.0) -> Pairs:
    """Pairs of the exact ZOH step of the plant over jittered intervals (1 ms +- 30 %)."""
    rng = np.random.default_rng(seed)
    n = 400
    M, B, fp, fn = TRUE
    dt = 1e-3 * (1.0 + 0.3 * rng.uniform(-1, 1, n))
    v0 = rng.normal(0.0, 2.0, n)
    v0[np.abs(v0) < 0.05] = 0.3  # clear motion in every pair
    u = 2.0 * np.sign(rng.normal(size=n))
    pos, neg = v0 > 0, v0 < 0
    a = np.exp(-B * dt / M)
    v1 = a * v0 + (1.0 - a) / B * (u - fp * pos + fn * neg) + noise * rng.normal(size=n)
    return Pairs(v0, v1, u, pos, neg, dt, v0)


@pytest.mark.parametrize("weighted", [False, True])
def test_the_jacobian_is_the_residuals_derivative(weighted):
    pairs = _pairs(1, noise=1e-3)
    w = np.random.default_rng(2).uniform(0.2, 2.0, len(pairs)) if weighted else 1.0
    problem = IrregularPairs(pairs, w, (math.log(0.012), math.log(0.9)))
    for p in ([math.log(0.012), math.log(0.9), 0.3, 0.2], [math.log(0.01), 0.0, 0.5, 0.4],
              [math.log(0.05), math.log(3.0), -0.1, 0.7]):  # fmt: skip
        numeric = approx_derivative(problem.residual, np.asarray(p), method="3-point")
        analytic = problem.jacobian(np.asarray(p))
        assert np.max(np.abs(analytic - numeric)) <= 1e-7 * np.max(np.abs(analytic))


def test_the_jacobian_is_zero_where_the_log_is_held_at_its_bound():
    problem = IrregularPairs(_pairs(3), 1.0, (math.log(0.01), 0.0))
    beyond = np.array([math.log(0.01) + DIVERGED_LOG + 1.0, 0.0, 0.5, 0.4])
    J = problem.jacobian(beyond)
    assert np.all(J[:, 0] == 0.0) and np.any(J[:, 1] != 0.0)
    numeric = approx_derivative(problem.residual, beyond, method="3-point")
    assert np.max(np.abs(numeric[:, 0])) == 0.0  # the residual is flat there too


def test_the_fit_recovers_the_exact_plant_from_a_start_off():
    fit = fit_pairs_irregular(_pairs(4), (0.012, 1.2, 0.4, 0.5))
    assert [fit.M, fit.B, fit.coulomb_pos, fit.coulomb_neg] == pytest.approx(TRUE, rel=1e-9)
    assert np.max(np.abs(fit.residual)) < 1e-12


def _cost(problem: IrregularPairs, x: np.ndarray) -> float:
    r = problem.residual(x)
    return float(r @ r)


def _lm(problem: IrregularPairs, start) -> np.ndarray:
    """scipy's Levenberg-Marquardt on the four unknowns, converged to rounding."""
    x0 = [math.log(start[0]), math.log(start[1]), start[2], start[3]]
    return least_squares(problem.residual, x0, jac=problem.jacobian, method="lm", xtol=1e-15,
                         ftol=1e-15, gtol=1e-15, max_nfev=10_000).x  # fmt: skip


@pytest.mark.parametrize("seed", [5, 6, 7])
@pytest.mark.parametrize("weighted", [False, True])
def test_the_projection_reaches_the_minimum_of_the_full_problem(seed, weighted):
    pairs = _pairs(seed, noise=0.02)
    w = np.random.default_rng(seed).uniform(0.2, 2.0, len(pairs)) if weighted else 1.0
    start = (0.013, 0.8, 0.3, 0.6)
    problem = IrregularPairs(pairs, w, (math.log(start[0]), math.log(start[1])))
    ours, theirs = _projected(problem, start), _lm(problem, start)
    assert ours == pytest.approx(theirs, rel=1e-7, abs=1e-9)
    assert _cost(problem, ours) <= _cost(problem, theirs) * (1.0 + 1e-12)
    fit = fit_pairs_irregular(pairs, start, None if not weighted else w**2)
    assert [math.log(fit.M), math.log(fit.B), fit.coulomb_pos, fit.coulomb_neg] == pytest.approx(ours, rel=1e-12)


def test_a_direction_without_motion_keeps_its_start():
    p = _pairs(8, noise=0.01)
    keep = p.v0 > 0
    pairs = Pairs(p.v0[keep], p.v1[keep], p.u[keep], p.pos[keep], p.neg[keep], p.dt[keep], p.z0[keep])
    start = (0.012, 1.1, 0.45, 0.123)
    problem = IrregularPairs(pairs, 1.0, (math.log(start[0]), math.log(start[1])))
    ours, theirs = _projected(problem, start), _lm(problem, start)
    assert ours[3] == 0.123 and theirs[3] == pytest.approx(0.123, rel=1e-12)
    assert ours[:3] == pytest.approx(theirs[:3], rel=1e-7)


def test_a_command_that_does_not_drive_the_velocity_gives_the_bounded_least_sum():
    p = _pairs(9, noise=0.01)
    u = -p.u  # the command against the motion: the least sum wants 1/B < 0
    pairs = Pairs(p.v0, p.v1, u, p.pos, p.neg, p.dt, p.z0)
    start = (0.01, 1.0, 0.5, 0.4)
    problem = IrregularPairs(pairs, 1.0, (math.log(start[0]), math.log(start[1])))
    ours = _projected(problem, start)
    assert ours is not None and math.exp(ours[1]) > 1e12  # B near the bound, finite
    theirs = least_squares(problem.residual, [math.log(0.01), 0.0, 0.5, 0.4], jac=problem.jacobian,
                           method="lm", xtol=1e-14, ftol=1e-14).x  # fmt: skip
    assert _cost(problem, ours) <= _cost(problem, theirs)
