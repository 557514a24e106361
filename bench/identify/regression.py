"""The exact sampled-data regression of the servo with Coulomb friction.

Between two samples in which the velocity keeps one strict sign (no zero
crossing, no sticking inside the interval) the friction force is constant
and the zero-order-hold solution is exact::

    v[k+1] = a v[k] + b u[k] - b coulomb_pos      (v > 0)
    v[k+1] = a v[k] + b u[k] + b coulomb_neg      (v < 0)

with ``a = exp(-B dt/M)`` and ``b = (1 - a)/B``. Stacking such pairs gives
a linear least-squares problem in ``(a, b, b coulomb_pos, b coulomb_neg)`` that is
exact for noise-free data at any amplitude. With sensor noise the pairs
are chosen on a noise-free reference (a simulation) and solved with
instrumental variables; the output-error refinement in
:mod:`servobench.bench.identify.output_error` then removes what is left.

In closed loop the command itself carries noise: the hold loop feeds the
measured motion back into ``u``, so ``u[k]`` is correlated with the noise
of ``v[k]`` that the pair's equation error holds, and least squares (which
uses ``u`` as its own instrument) is biased. There the excitation ``u_exc``,
which no noise reaches, is the instrument of ``u``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from servobench.errors import IdentificationError

#: MAD to standard deviation for Gaussian noise.
MAD_TO_STD = 1.482602218505602


@dataclass(frozen=True)
class Pairs:
    """Sample pairs ``(k, k+1)`` usable in the exact regression, all runs stacked.

    Attributes
    ----------
    v0, v1 : ndarray
        Measured velocity at ``k`` and ``k+1`` [units/s].
    u : ndarray
        Command held over the interval [command units].
    pos, neg : ndarray of bool
        Interval in positive / negative motion.
    dt : ndarray
        Interval length [s].
    z0 : ndarray
        Instrument for ``v0`` (the reference velocity at ``k``; ``v0`` itself for plain LS).
    zu : ndarray or None
        Instrument for ``u`` (the excitation of a closed-loop log); None: ``u`` itself.
    sigma_dt : ndarray or None
        1-sigma uncertainty of each interval [s] (from the instants' ``t_unc``); None: exact.
    """

    v0: np.ndarray
    v1: np.ndarray
    u: np.ndarray
    pos: np.ndarray
    neg: np.ndarray
    dt: np.ndarray
    z0: np.ndarray
    zu: np.ndarray | None = None
    sigma_dt: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.v0.size)


def select_pairs(
    velocities: Sequence[np.ndarray],
    commands: Sequence[np.ndarray],
    intervals: Sequence[np.ndarray],
    references: Sequence[np.ndarray] | None = None,
    threshold: float = 0.0,
    max_pairs: int | None = None,
    excitations: Sequence[np.ndarray] | None = None,
    interval_sigmas: Sequence[np.ndarray] | None = None,
) -> Pairs:
    """Pairs whose reference velocity keeps one strict sign with ``|v| > threshold`` at both ends.

    Parameters
    ----------
    velocities, commands : sequences of ndarray, one per run
        Measured velocity [units/s] and command [command units].
    intervals : sequence of ndarray, shape ``(n - 1,)`` each
        Sample intervals [s].
    references : sequence of ndarray, optional
        Noise-free velocities used to choose the pairs and as instruments.
    threshold : float
        Smallest ``|reference|`` accepted at both ends [units/s].
    max_pairs : int, optional
        Consider only every ``ceil(n / max_pairs)``-th interval (even thinning).
    excitations : sequence of ndarray, optional
        Closed loop: the excitation of each run [command units], the instrument of ``u``.
    interval_sigmas : sequence of ndarray, shape ``(n - 1,)`` each, optional
        1-sigma uncertainty of each interval [s] (:func:`interval_sigma`).
    """
    refs = velocities if references is None else references
    exc = commands if excitations is None else excitations
    total = sum(len(v) - 1 for v in velocities)
    step = 1 if max_pairs is None or total <= max_pairs else -(-total // max_pairs)
    sig = intervals if interval_sigmas is None else interval_sigmas
    parts: list[list[np.ndarray]] = [[] for _ in range(9)]
    for v, u, dt, r, e, sd in zip(velocities, commands, intervals, refs, exc, sig, strict=True):
        k = np.arange(0, len(v) - 1, step) if step > 1 else slice(0, len(v) - 1)
        k1 = k + 1 if step > 1 else slice(1, len(v))
        r0, r1 = r[k], r[k1]
        pos = (r0 > threshold) & (r1 > threshold)
        neg = (r0 < -threshold) & (r1 < -threshold)
        keep = pos | neg
        for i, arr in enumerate((v[k], v[k1], u[k], pos, neg, dt[k], r0, e[k], sd[k])):
            parts[i].append(arr[keep])
    v0, v1, u, pos, neg, dt, z0, zu, sd = (np.concatenate(p) for p in parts)
    return Pairs(v0, v1, u, pos, neg, dt, z0, None if excitations is None else zu,
                 None if interval_sigmas is None else sd)  # fmt: skip


def interval_sigma(t_unc: np.ndarray) -> np.ndarray:
    """1-sigma uncertainty [s] of each interval ``t[k+1] - t[k]``, shape ``(n - 1,)``, from the
    half-widths ``t_unc`` [s] of the intervals holding each instant (uniform within them)."""
    var = np.asarray(t_unc, dtype=float) ** 2 / 3.0
    return np.sqrt(var[:-1] + var[1:])


def timing_weights(
    pairs: Pairs, model: tuple[float, float, float, float], sigma_v: float
) -> np.ndarray:
    """Weights of the pairs for an interval known only to ``pairs.sigma_dt``.

    A pair's equation error from an interval off by ``d`` is the velocity's
    change over ``d``, the acceleration ``acc = (u - F - B v1) / M`` times
    ``d``; with velocity noise ``sigma_v`` the error's variance is
    ``sigma_v^2 (1 + a^2) + (acc sigma_dt)^2``. The weights are its inverse,
    scaled to mean 1 (ones without ``sigma_dt``).
    """
    if pairs.sigma_dt is None:
        return np.ones(len(pairs))
    M, B, fp, fn = model
    force = np.where(pairs.pos, fp, 0.0) - np.where(pairs.neg, fn, 0.0)
    acc = (pairs.u - force - B * pairs.v1) / M
    timing_var = (acc * pairs.sigma_dt) ** 2
    a = np.exp(-B * pairs.dt / M)
    # a floor keeps pairs at zero acceleration from outweighing all the others
    floor = 1e-2 * float(np.median(timing_var)) if timing_var.size else 0.0
    var = np.maximum(sigma_v**2 * (1.0 + a * a) + timing_var, max(floor, 1e-300))
    w = 1.0 / var
    return w / float(np.mean(w))


@dataclass(frozen=True)
class ZohFit:
    """Physical parameters from the regression, their covariance and the residual.

    ``theta`` is ``(a, b, b*coulomb_pos, b*coulomb_neg)``; ``cov`` its covariance.
    """

    M: float
    B: float
    coulomb_pos: float
    coulomb_neg: float
    theta: np.ndarray
    cov: np.ndarray
    residual: np.ndarray
    pairs: int

    def physical_std(self, dt_s: float) -> dict[str, float]:
        """1-sigma of ``M``, ``B``, ``coulomb_pos``, ``coulomb_neg`` by the delta method."""
        J = physical_jacobian(self.theta, dt_s)
        cov = J @ self.cov @ J.T
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        return {
            "M": float(sd[0]),
            "B": float(sd[1]),
            "coulomb_pos": float(sd[2]),
            "coulomb_neg": float(sd[3]),
        }


def to_physical(theta: np.ndarray, dt_s: float) -> tuple[float, float, float, float]:
    """``(a, b, b coulomb_pos, b coulomb_neg)`` -> ``(M, B, coulomb_pos, coulomb_neg)``."""
    a, b, cp, cn = (float(x) for x in theta)
    if not (0.0 < a < 1.0) or not b > 0.0:
        raise IdentificationError(
            f"the regression gives a = {a:.6g}, b = {b:.4g}: not a damped plant driven by u "
            "(check the sign of u and v, and that the log holds motion)"
        )
    B = (1.0 - a) / b
    M = -B * dt_s / math.log(a)
    return M, B, cp / b, cn / b


def physical_jacobian(theta: np.ndarray, dt_s: float) -> np.ndarray:
    """Numerical Jacobian of :func:`to_physical` (4 x 4)."""
    base = np.array(to_physical(theta, dt_s))
    J = np.zeros((4, 4))
    for i in range(4):
        h = 1e-7 * max(abs(theta[i]), 1e-12)
        tp = np.array(theta, dtype=float)
        tp[i] += h
        J[:, i] = (np.array(to_physical(tp, dt_s)) - base) / h
    return J


def fit_pairs(pairs: Pairs, dt_s: float, instrumental: bool = False) -> ZohFit:
    """Solve the regression by least squares, or by instrumental variables (``z0`` for ``v0``,
    and ``zu`` for ``u`` when the pairs carry it).

    Normal equations on scaled columns with one step of iterative refinement:
    as accurate as an orthogonal solve for these four well-scaled columns, and
    fast for millions of pairs.
    """
    n = len(pairs)
    if n < 8:
        raise IdentificationError(
            f"only {n} sample pairs with clear motion: the axis barely moved (raise the amplitude)"
        )
    if not pairs.pos.any() and not pairs.neg.any():
        raise IdentificationError("no motion in the data")
    X = np.empty((n, 4))
    X[:, 0] = pairs.v0
    X[:, 1] = pairs.u
    X[:, 2] = pairs.pos
    X[:, 2] *= -1.0
    X[:, 3] = pairs.neg
    used = [i for i in range(4) if np.any(X[:, i] != 0)]
    Xu = X if len(used) == 4 else X[:, used]
    if instrumental:
        Zu = Xu.copy()
        Zu[:, 0] = pairs.z0
        if pairs.zu is not None and 1 in used:
            Zu[:, used.index(1)] = pairs.zu
    else:
        Zu = Xu
    y = pairs.v1
    scale = np.sqrt(np.einsum("ij,ij->j", Xu, Xu) / n)
    scale[scale == 0] = 1.0
    G = (Zu.T @ Xu) / np.outer(scale, scale)
    try:
        ths = np.linalg.solve(G, (Zu.T @ y) / scale)
        th_u = ths / scale
        r = y - Xu @ th_u
        th_u = th_u + np.linalg.solve(G, (Zu.T @ r) / scale) / scale
    except np.linalg.LinAlgError as err:
        raise IdentificationError(
            f"the regression is singular ({err}); the data lack excitation"
        ) from None
    theta = np.zeros(4)
    theta[used] = th_u
    residual = y - Xu @ th_u
    dof = max(1, n - len(used))
    s2 = float(residual @ residual) / dof
    try:
        inv = np.linalg.inv(G)
        ZZ = (Zu.T @ Zu) / np.outer(scale, scale)
        cov_u = s2 * (inv @ ZZ @ inv.T) / np.outer(scale, scale)
    except np.linalg.LinAlgError:
        cov_u = np.full((len(used), len(used)), np.nan)
    cov = np.zeros((4, 4))
    cov[np.ix_(used, used)] = cov_u
    M, B, fp, fn = to_physical(theta, dt_s)
    return ZohFit(M, B, fp, fn, theta, cov, residual, n)


def noise_std_from_residual(residual: np.ndarray, a: float) -> float:
    """Velocity noise sigma from the regression residual ``e[k+1] - a e[k]`` (robust, MAD)."""
    if residual.size == 0:
        return 0.0
    r = residual - np.median(residual)
    return float(MAD_TO_STD * np.median(np.abs(r)) / math.sqrt(1.0 + a * a))


#: A fit of M or B that moves this many e-folds from its start has diverged [natural log].
DIVERGED_LOG = 30.0


@dataclass(frozen=True)
class IrregularPairs:
    """The pair residual on irregular intervals and its Jacobian, in the unknowns
    ``p = (ln M, ln B, coulomb_pos, coulomb_neg)``: ``root_w (v1 - a v0 - b (u - coulomb_pos pos
    + coulomb_neg neg))`` with ``a = exp(-B dt / M)``, ``b = (1 - a) / B``. ``ln M`` and ``ln B``
    are held within :data:`DIVERGED_LOG` of ``start_log`` (beyond, ``exp`` overflows: a diverged
    step), where the Jacobian's column is zero."""

    pairs: Pairs
    root_w: np.ndarray | float
    start_log: tuple[float, float]

    @property
    def lo(self) -> np.ndarray:
        return np.asarray(self.start_log) - DIVERGED_LOG

    @property
    def hi(self) -> np.ndarray:
        return np.asarray(self.start_log) + DIVERGED_LOG

    def _terms(self, p: np.ndarray):
        lo, hi = self.lo, self.hi
        M, B = math.exp(min(max(p[0], lo[0]), hi[0])), math.exp(min(max(p[1], lo[1]), hi[1]))
        x = B * self.pairs.dt / M
        a = np.exp(-x)
        b = (1.0 - a) / B
        U = self.pairs.u - p[2] * self.pairs.pos + p[3] * self.pairs.neg
        return B, x, a, b, U

    def residual(self, p: np.ndarray) -> np.ndarray:
        _, _, a, b, U = self._terms(p)
        return self.root_w * (self.pairs.v1 - a * self.pairs.v0 - b * U)

    def jacobian(self, p: np.ndarray) -> np.ndarray:
        """d residual / d p, shape ``(pairs, 4)``: ``da/dln M = a x = -da/dln B`` (``x = B dt /
        M``), ``db/dln M = -a x / B``, ``db/dln B = a x / B - b``."""
        B, x, a, b, U = self._terms(p)
        ax = a * x * (self.pairs.v0 - U / B)
        lo, hi = self.lo, self.hi
        J = np.empty((self.pairs.v1.size, 4))
        J[:, 0] = -ax if lo[0] < p[0] < hi[0] else 0.0
        J[:, 1] = ax + b * U if lo[1] < p[1] < hi[1] else 0.0
        J[:, 2] = b * self.pairs.pos
        J[:, 3] = -b * self.pairs.neg
        return J * (self.root_w if np.ndim(self.root_w) == 0 else np.asarray(self.root_w)[:, None])


#: The variable projection's search on ``ln(B/M)``: its tolerance, and the Gauss-Newton
#: steps on all four unknowns that polish its result to the full problem's rounding.
PROJECTION_XTOL = 1e-10
POLISH_STEPS = 3


def _projected(problem: IrregularPairs, start: tuple[float, float, float, float]) -> np.ndarray | None:
    """The pair regression on irregular intervals by variable projection: ``p = (ln M, ln B,
    coulomb_pos, coulomb_neg)`` at the least residual sum, or None where the search fails.

    For a pole ``lam = B/M`` the residual ``root_w (v1 - a v0 - (1 - a)(u/B - coulomb_pos/B pos
    + coulomb_neg/B neg))``, ``a = exp(-lam dt)``, is linear in ``(1/B, coulomb_pos/B,
    coulomb_neg/B)``: the sum is minimised over ``ln lam`` alone (Brent), each trial one small
    linear solve, and Gauss-Newton steps on all four unknowns (the analytic Jacobian) finish
    where the one-dimensional search stops. A direction without motion in any pair keeps its
    Coulomb level at ``start``, as the full problem's zero gradient there does. Where the least
    sum wants ``1/B <= 0`` (a trial delay at which the command does not drive the velocity), the
    bounded problem's infimum at ``1/B -> 0`` is returned. The same minimum as
    :func:`scipy.optimize.least_squares` on the four unknowns, at a fraction of its cost
    (the delay scan runs hundreds of these fits per log).
    """
    from scipy.optimize import minimize_scalar

    P = problem.pairs
    w = problem.root_w
    M0, B0 = start[0], start[1]
    # the Coulomb levels (entries 2, 3 of p) of the directions with motion, and their columns
    moving = [(i, sign * np.asarray(mask, dtype=float))
              for i, mask, sign in ((2, P.pos, -1.0), (3, P.neg, 1.0)) if np.any(mask)]  # fmt: skip
    coulomb = [i for i, _ in moving]
    C = np.stack([np.asarray(P.u, dtype=float), *(col for _, col in moving)], axis=1)
    dt = np.asarray(P.dt, dtype=float)
    v0 = np.asarray(P.v0, dtype=float)
    v1 = np.asarray(P.v1, dtype=float)

    def least(X: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray]:
        try:
            c = np.linalg.solve(X.T @ X, X.T @ y)
        except np.linalg.LinAlgError:
            return math.inf, np.full(X.shape[1], np.nan)
        e = y - X @ c
        cost = float(e @ e)
        return (cost, c) if math.isfinite(cost) else (math.inf, c)

    def solve(s: float) -> tuple[float, np.ndarray]:
        """The least sum at ``ln lam = s`` with ``1/B >= 0``, and its linear unknowns."""
        a = np.exp(-math.exp(s) * dt)
        y = w * (v1 - a * v0)
        X = (w * (1.0 - a))[:, None] * C
        cost, c = least(X, y)
        if c[0] > 0.0 or not np.all(np.isfinite(c)):
            return cost, c
        # the sum wants 1/B <= 0 (the command does not drive the velocity at this trial): the
        # bounded least sum lies at 1/B = 0, the command's column dropped
        cost, rest = least(X[:, 1:], y)
        return cost, np.concatenate(([0.0], rest))

    s0 = math.log(B0 / M0)
    try:  # a trial whose solve fails is an infinite sum: Brent's parabola steps past it
        with np.errstate(all="ignore"):
            res = minimize_scalar(lambda s: solve(s)[0], bracket=(s0, s0 + 0.01), method="brent",
                                  options={"xtol": PROJECTION_XTOL})  # fmt: skip
    except (ValueError, RuntimeError, FloatingPointError):
        return None
    s = float(res.x)
    if not (math.isfinite(s) and abs(s - s0) < DIVERGED_LOG):
        return None
    _, c = solve(s)
    if not np.all(np.isfinite(c)):
        return None
    # at 1/B = 0 the fit is returned at B one e-fold inside the divergence bound above its start
    # (the sum's rise there is below its rounding; the full problem's steps stall short of it)
    bound = not c[0] > 0.0
    B = B0 * math.exp(DIVERGED_LOG - 1.0) if bound else 1.0 / c[0]
    x = np.array([math.log(B) - s, math.log(B), start[2], start[3]], dtype=float)
    x[coulomb] = c[1:] * B
    if not np.all(np.isfinite(x)):
        return None
    if bound:
        return x
    free = [0, 1, *coulomb]
    r = problem.residual(x)
    cost = float(r @ r)
    for _ in range(POLISH_STEPS):
        J = problem.jacobian(x)[:, free]
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        trial = x.copy()
        trial[free] += step
        r_t = problem.residual(trial)
        cost_t = float(r_t @ r_t)
        if not cost_t < cost:
            break
        x, r, cost = trial, r_t, cost_t
    return x


def fit_pairs_irregular(
    pairs: Pairs, start: tuple[float, float, float, float], weights: np.ndarray | None = None
) -> ZohFit:
    """The regression with a different interval per pair, by nonlinear least squares.

    Unknowns ``(M, B, coulomb_pos, coulomb_neg)``; ``a_k = exp(-B dt_k/M)``,
    ``b_k = (1 - a_k)/B``; exact for noise-free data. ``weights`` (one per
    pair, e.g. :func:`timing_weights`) weight the squared equation errors.
    Solved by variable projection (:func:`_projected`); Levenberg-Marquardt on
    the four unknowns from ``start`` where that search fails.
    """
    from scipy.optimize import least_squares

    if len(pairs) < 8:
        raise IdentificationError(
            f"only {len(pairs)} sample pairs with clear motion (raise the amplitude)"
        )
    M0, B0, fp0, fn0 = start
    problem = IrregularPairs(pairs, 1.0 if weights is None else np.sqrt(weights), (math.log(M0), math.log(B0)))
    lo, hi = problem.lo, problem.hi
    x = _projected(problem, start)
    if x is None:  # the projection's search failed: the full problem from the start
        x = least_squares(problem.residual, [math.log(M0), math.log(B0), fp0, fn0], jac=problem.jacobian,
                          method="lm", xtol=1e-14, ftol=1e-14).x  # fmt: skip
    if not (np.all(np.isfinite(x)) and np.all(x[:2] > lo) and np.all(x[:2] < hi)):
        raise IdentificationError(
            f"the pair regression on irregular intervals diverged from M {M0:.4g}, B {B0:.4g}: "
            "too few pairs with clear motion between the host's stalls (raise the amplitude)"
        )
    M, B, fp, fn = math.exp(x[0]), math.exp(x[1]), float(x[2]), float(x[3])
    dt = float(np.mean(pairs.dt))
    a = math.exp(-B * dt / M)
    b = (1.0 - a) / B
    theta = np.array([a, b, b * fp, b * fn])
    r = problem.residual(x)
    jac = problem.jacobian(x)
    s2 = float(r @ r) / max(1, r.size - 4)
    try:  # a degenerate problem (a trial grid's draw) leaves no finite covariance: NaN, quietly
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            cov_p = s2 * np.linalg.inv(jac.T @ jac)
            # p -> theta through the physical parameters
            Jt = np.linalg.inv(physical_jacobian(theta, dt)) @ np.diag([M, B, 1.0, 1.0])
            cov = Jt @ cov_p @ Jt.T
    except np.linalg.LinAlgError:
        cov = np.full((4, 4), np.nan)
    return ZohFit(M, B, fp, fn, theta, cov, r, len(pairs))
