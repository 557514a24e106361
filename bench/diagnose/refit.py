"""Refit every parameter of a candidate on simulation error (``scipy.optimize.least_squares``).

The parameters are scaled to order one (``M`` and ``B`` on a log scale) so a
single relative finite-difference step suits them all; the step is large
enough (1e-3) to see through the kinks stick-slip puts into the error
surface. Stick-slip and impacts make the surface rugged, where a trust
region shrinks early: the gradient fit restarts while it keeps gaining.

Parameters a screening marks *fixed* (a quantization step, on which the error
is piecewise constant) are searched on a small grid after the gradient fit.
Candidates with *scan* parameters (a play that closes or not before a
reversal, cogging wells that hold the axis) get a coordinate search of those, then
of the base friction and inertia, before it (an angle, a cogging phase, by offsets in
radians, not factors), and a Nelder-Mead polish after it;
the gradient fit from the start itself is kept where it ends lower. Only training samples
enter the cost; held-out samples judge the result.

The Jacobian is ``least_squares``'s own two-point finite difference (same steps, same
columns), its columns simulated in one compiled call (:func:`.simulate.simulate_flat`)
instead of one simulation per column.

Every fitted parameter gets a 1-sigma (:mod:`.sigma`): the noise-model sandwich of the Jacobian
and residual of the final ``least_squares`` (a fresh Jacobian when the grid search or an earlier
round's solution is kept), each window a chunk, with the simulation's sensitivity to the measured
velocity each window starts from, in natural units by the chain rule.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from servobench.bench.diagnose.data import REFIT_MAX_SAMPLES, DiagnosisData
from servobench.bench.diagnose.sigma import ParameterCovariance, natural_covariance
from servobench.bench.diagnose.simulate import (
    BASE_KEYS,
    Candidate,
    Window,
    gap_percent,
    simulate,
    simulate_flat,
    thinned,
    windows,
)
from servobench.errors import UsageError
from servobench.sim_backend.physics import effects as library

#: Relative finite-difference step of the Jacobian.
DIFF_STEP = 1e-3
#: Cost evaluations (not counting Jacobian columns) per refit.
MAX_NFEV = 12
#: Key of the base parameters in coordinate searches, and which of them are searched.
BASE = "base"
BASE_SCAN = ("coulomb_pos", "coulomb_neg", "M")
#: Gradient fits restarted (fresh trust region) while each gains this share of the cost.
RESTARTS = 3
RESTART_GAIN = 0.02
#: Nelder-Mead polish of rugged candidates: initial simplex edge (scaled units) and budget.
SIMPLEX_STEP = 0.05
SIMPLEX_MAXFEV = 200
#: ... unless the gradient fit already reached this multiple of the noise floor.
POLISH_ABOVE = 1.5
#: The Coulomb levels' least scale in a fit, as a share of the command's spread.
FORCE_FLOOR_SHARE = 0.05
#: Step of the start velocity's sensitivity (:meth:`_TrainingError.start_gain`), a share of the
#: velocity's spread.
START_STEP = 1e-3
#: Residual returned for parameters the simulator rejects.
PENALTY = 10.0
#: Multipliers tried for fixed (grid-searched) parameters after the gradient fit.
GRID = (0.94, 0.97, 0.985, 1.015, 1.03, 1.06)
#: Multipliers tried for rugged (scanned) parameters before it.
COARSE = (0.6, 0.75, 0.9, 1.1, 1.25, 1.5)
#: Offsets [rad] tried for angles (a parameter in ``rad``, such as a cogging phase) in place of
#: multipliers, which would not move an angle near 0: before the gradient fit, a span a
#: screening's phase may miss by; after it, the steps between its iterates.
ANGLE_COARSE = tuple(round(k * 0.03, 2) for k in range(-10, 11) if k)
ANGLE_GRID = (-0.02, -0.01, 0.01, 0.02)

Bounds = Mapping[str, Mapping[str, tuple[float, float]]]


@dataclass(frozen=True)
class FitResult:
    """A fitted candidate, its simulated velocity per run and its gaps [%].

    ``covariance`` (of a :func:`refit`; None for a candidate only evaluated) holds the fitted
    parameters' covariance, ``std`` their 1-sigma by name (``M``, ``B``, ``coulomb_pos``,
    ``coulomb_neg``, ``"effect.parameter"``; parameters held fixed have none, those the data
    do not determine NaN).
    """

    candidate: Candidate
    v_sim: tuple[np.ndarray, ...]
    gap: float
    gap_train: float
    gap_held_out: float
    evaluations: int
    #: Computes :attr:`covariance` when first asked for (None: no covariance).
    covariance_of: Callable[[], ParameterCovariance | None] | None = field(
        default=None, repr=False, compare=False
    )

    @cached_property
    def covariance(self) -> ParameterCovariance | None:
        """The fitted parameters' covariance, computed on first use: a search refits scores of
        candidates and compares them, and reads the sigma of few."""
        return None if self.covariance_of is None else self.covariance_of()

    @property
    def std(self) -> dict[str, float]:
        return {} if self.covariance is None else self.covariance.std


def evaluate(
    data: DiagnosisData,
    cand: Candidate,
    evaluations: int = 1,
    covariance_of: Callable[[], ParameterCovariance | None] | None = None,
) -> FitResult:
    """Simulate a candidate on all windows and measure its gaps (infinite for parameters the
    simulator rejects); ``covariance_of`` computes the parameters' covariance when it is first
    asked for (:attr:`FitResult.covariance`)."""
    try:
        v = tuple(simulate(data, cand))
    except UsageError:
        inf = float("inf")
        return FitResult(
            cand, tuple(np.full(len(r), np.nan) for r in data.segments), inf, inf, inf, evaluations
        )
    return FitResult(
        cand,
        v,
        gap_percent(data, v, "all"),
        gap_percent(data, v, "train"),
        gap_percent(data, v, "held_out"),
        evaluations,
        covariance_of,
    )


def training_windows(data: DiagnosisData) -> list[Window]:
    """Fitting windows that carry training samples, thinned to about :data:`REFIT_MAX_SAMPLES`."""
    chosen = [w for w in windows(data, fit=True) if not data.held_out[w[0]][w[1] : w[2]].all()]
    return thinned(chosen, REFIT_MAX_SAMPLES)


class _Layout:
    """Mapping between a candidate and the scaled parameter vector ``z``."""

    def __init__(
        self,
        cand: Candidate,
        bounds: Bounds,
        fixed: Mapping[str, tuple[str, ...]],
        force_floor: float = 0.0,
    ) -> None:
        self.cand = cand
        #: (effect, parameter, scale, low, high) of each fitted effect parameter.
        self.slots: list[tuple[str, str, float, float, float]] = []
        b = cand.base
        # the Coulomb levels' scale: their own size, and never below the log's force floor (a
        # start without friction would otherwise scale them by 1e-3 B, where a trust region
        # cannot reach a level of the command's size: a play's closed-loop log kept 0.0 / 0.006
        # for 0.28 / 0.43, diagnose_cases.py #164)
        fscale = max(abs(b["coulomb_pos"]), abs(b["coulomb_neg"]), 1e-3 * b["B"], force_floor, 1e-12)
        self.fscale = fscale
        for name, values in cand.effects.items():
            for pname, value in values.items():
                if pname in fixed.get(name, ()) or pname not in bounds.get(name, {}):
                    continue
                lo, hi = bounds[name][pname]
                scale = max(abs(value), (hi - lo) / 20.0, 1e-12)
                self.slots.append((name, pname, scale, lo, hi))

    def start(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        b = self.cand.base
        z = [0.0, 0.0, b["coulomb_pos"] / self.fscale, b["coulomb_neg"] / self.fscale]
        lo = [-math.log(100.0), -math.log(100.0), 0.0, 0.0]
        hi = [math.log(100.0), math.log(100.0), np.inf, np.inf]
        for name, pname, scale, plo, phi in self.slots:
            value = self.cand.effects[name][pname]
            z.append(min(max(value, plo), phi) / scale)
            lo.append(plo / scale)
            hi.append(phi / scale)
        z0 = np.clip(np.array(z), np.array(lo), np.array(hi))
        return z0, np.array(lo), np.array(hi)

    def names(self) -> tuple[str, ...]:
        """The natural parameter of each entry of ``z``, as the model file names them."""
        return (*BASE_KEYS, *(f"{name}.{pname}" for name, pname, *_ in self.slots))

    def dnatural_dz(self, z: np.ndarray) -> np.ndarray:
        """``d natural / d z`` of each parameter at ``z`` (each depends on its own entry alone:
        ``M`` and ``B`` on a log scale, the others scaled)."""
        b = self.cand.base
        scales = [self.fscale, self.fscale, *(scale for _, _, scale, _, _ in self.slots)]
        return np.array([b["M"] * math.exp(z[0]), b["B"] * math.exp(z[1]), *scales])

    def candidate(self, z: np.ndarray) -> Candidate:
        b = self.cand.base
        base = {
            "M": b["M"] * math.exp(z[0]),
            "B": b["B"] * math.exp(z[1]),
            "coulomb_pos": z[2] * self.fscale,
            "coulomb_neg": z[3] * self.fscale,
        }
        effects = {name: dict(values) for name, values in self.cand.effects.items()}
        for (name, pname, scale, _, _), value in zip(self.slots, z[4:], strict=True):
            effects[name][pname] = float(value * scale)
        for name in effects:
            effects[name] = library.project(name, effects[name], base)
        return Candidate(base, effects)


def _simplex(cand: Candidate, bounds: Bounds, fixed, error: _TrainingError) -> tuple[Candidate, float]:
    """Nelder-Mead polish in the scaled parameters, for surfaces too rugged for gradients."""
    from scipy.optimize import minimize

    cost = error.cost
    layout = _Layout(cand, bounds, fixed, error.force_floor)
    z0, lo, hi = layout.start()
    steps = SIMPLEX_STEP * np.maximum(1.0, np.abs(z0))
    simplex = np.vstack([z0, z0 + np.diag(steps)])
    sol = minimize(
        lambda z: cost(layout.candidate(np.clip(z, lo, hi))),
        z0,
        method="Nelder-Mead",
        options={"initial_simplex": simplex, "maxfev": SIMPLEX_MAXFEV},
    )
    best = layout.candidate(np.clip(sol.x, lo, hi))
    return best, cost(best)


class _TrainingError:
    """Simulation error of candidates on the training samples, in units of the velocity's
    spread; counts the simulations."""

    def __init__(self, data: DiagnosisData) -> None:
        self.data = data
        self.which = training_windows(data)
        self.masks = [~data.held_out[i][s:e] for i, s, e in self.which]
        self._flat_mask = np.concatenate(self.masks) if self.masks else np.zeros(0, dtype=bool)
        self.measured = self._training([s.v for s in data.segments])
        self.scale = float(np.std(data.cat("v")))
        #: The least scale of the Coulomb levels in a fit: :data:`FORCE_FLOOR_SHARE` of the
        #: command's spread [command units].
        self.force_floor = FORCE_FLOOR_SHARE * float(np.std(data.cat("u")))
        self.evaluations = 0

    def _training(self, per_run: Sequence[np.ndarray]) -> np.ndarray:
        """The training samples of one array per run, concatenated."""
        return np.concatenate(
            [per_run[i][s:e][m] for (i, s, e), m in zip(self.which, self.masks, strict=True)]
        )

    def residuals(self, cands: Sequence[Candidate]) -> list[np.ndarray]:
        """:meth:`residual` of each candidate, simulated in one batch."""
        self.evaluations += len(cands)
        out = []
        for v in simulate_flat(self.data, cands, self.which):
            if isinstance(v, UsageError):
                out.append(np.full(self.measured.size, PENALTY))
                continue
            r = (v[self._flat_mask] - self.measured) / self.scale
            out.append(np.where(np.isfinite(r), r, PENALTY))
        return out

    def residual(self, cand: Candidate) -> np.ndarray:
        return self.residuals([cand])[0]

    @property
    def chunks(self) -> np.ndarray:
        """Cumulative sizes of each window's training samples in the residual."""
        return np.cumsum([int(m.sum()) for m in self.masks])

    @property
    def window_ends(self) -> np.ndarray:
        """Cumulative sizes of the windows, every sample (held-out ones too)."""
        return np.cumsum([e - s for _, s, e in self.which])

    @property
    def training_mask(self) -> np.ndarray:
        """Which samples of the windows, each after the one before it, are training samples."""
        return self._flat_mask

    def start_gain(self, cand: Candidate) -> np.ndarray | None:
        """How much ``cand``'s simulated velocity at every sample of the windows moves with the
        measured velocity its window starts from (central difference, :data:`START_STEP` of the
        velocity's spread); None where the simulator rejects the candidate."""
        step = START_STEP * self.scale
        if not step > 0.0:
            return None
        (hi,), (lo,) = (simulate_flat(self.data, [cand], self.which, start_dv=d) for d in (step, -step))
        if isinstance(hi, UsageError) or isinstance(lo, UsageError):
            return None
        return (hi - lo) / (2.0 * step)

    def cost(self, cand: Candidate) -> float:
        return float(np.sum(self.residual(cand) ** 2))

    def gap_percent(self, cost: float) -> float:
        """The training gap [%] a cost stands for."""
        return 100.0 * math.sqrt(cost / max(self.measured.size, 1))


def _with_value(cand: Candidate, name: str, pname: str, value: float) -> Candidate:
    """``cand`` with one parameter (of the base when ``name`` is :data:`BASE`) set to ``value``."""
    base, effects = dict(cand.base), {k: dict(v) for k, v in cand.effects.items()}
    if name == BASE:
        base[pname] = value
    else:
        effects[name][pname] = value
    return Candidate(base, effects)


def _is_angle(name: str, pname: str) -> bool:
    """Whether effect ``name``'s parameter ``pname`` is an angle (declared in ``rad``)."""
    return name != BASE and any(p.name == pname and p.unit == "rad" for p in library.spec(name).params)


def _line_search(
    error: _TrainingError,
    cand: Candidate,
    cost: float,
    params: Mapping[str, tuple[str, ...]],
    factors: tuple[float, ...],
    bounds: Bounds,
    angles: tuple[float, ...] = ANGLE_GRID,
) -> tuple[Candidate, float]:
    """Coordinate search: each parameter times each factor (an angle plus each of ``angles``
    [rad]), keeping what lowers the cost.

    A parameter's trials differ from the candidate in that parameter alone, whichever of them
    was kept, so they are simulated in one batch and kept in order as one at a time would be.
    """
    for name, pnames in params.items():
        for pname in pnames:
            if name != BASE and name not in cand.effects:
                continue
            centre = cand.base[pname] if name == BASE else cand.effects[name][pname]
            lo, hi = bounds.get(name, {}).get(pname, (-np.inf, np.inf))
            values = (
                [centre + a for a in angles]
                if _is_angle(name, pname)
                else [centre * factor for factor in factors]
            )
            trials = [_with_value(cand, name, pname, min(max(v, lo), hi)) for v in values]
            for trial, residual in zip(trials, error.residuals(trials), strict=True):
                trial_cost = float(np.sum(residual**2))
                if trial_cost < cost:
                    cand, cost = trial, trial_cost
    return cand, cost


class _Problem:
    """The residual of the scaled parameters for ``least_squares``, and its Jacobian with the
    columns in one batch.

    The Jacobian is ``least_squares``'s own: its two-point difference
    (``approx_derivative`` with ``rel_step`` :data:`DIFF_STEP` and the bounds, at the residual
    it has just evaluated) is run twice, once to learn the points it steps to, then on their
    residuals, simulated together: the same steps, the same columns, bit for bit.
    """

    def __init__(self, error: _TrainingError, layout: _Layout, lo: np.ndarray, hi: np.ndarray):
        self.error, self.layout, self.bounds = error, layout, (lo, hi)
        self.x: np.ndarray | None = None
        self.f: np.ndarray | None = None

    def fun(self, z: np.ndarray) -> np.ndarray:
        f = self.error.residual(self.layout.candidate(z))
        self.x, self.f = np.array(z, dtype=float), f
        return f

    def jac(self, z: np.ndarray) -> np.ndarray:
        from scipy.optimize._numdiff import approx_derivative

        f0 = self.f if self.x is not None and np.array_equal(self.x, z) else self.fun(z)
        points: list[np.ndarray] = []

        def record(x: np.ndarray) -> np.ndarray:
            points.append(np.array(x, dtype=float))
            return f0

        options = {"method": "2-point", "rel_step": DIFF_STEP, "f0": f0, "bounds": self.bounds}
        approx_derivative(record, z, **options)
        columns = iter(self.error.residuals([self.layout.candidate(x) for x in points]))
        return approx_derivative(lambda x: next(columns), z, **options)


@dataclass(frozen=True)
class _Solution:
    """A ``least_squares`` solution: the candidate, its layout, the scaled parameters, the
    Jacobian and residual there."""

    candidate: Candidate
    layout: _Layout
    z: np.ndarray
    jac: np.ndarray
    residual: np.ndarray


def _gradient_fit(
    error: _TrainingError,
    start: Candidate,
    start_cost: float,
    bounds: Bounds,
    fixed: Mapping[str, tuple[str, ...]],
    grid: Mapping[str, tuple[str, ...]],
    max_nfev: int,
) -> tuple[Candidate, float, _Solution | None]:
    """Trust-region fits of the scaled parameters, each followed by the grid search of
    ``grid``, restarted while a round gains :data:`RESTART_GAIN` of the cost; with the
    solution of the ``least_squares`` the best candidate is (None when the grid search
    moved it, or no fit gained)."""
    from scipy.optimize import least_squares

    best, best_cost, solution = start, start_cost, None
    for _ in range(RESTARTS):
        layout = _Layout(best, bounds, fixed, error.force_floor)
        z0, lo, hi = layout.start()
        problem = _Problem(error, layout, lo, hi)
        sol = least_squares(
            problem.fun,
            z0,
            jac=problem.jac,
            bounds=(lo, hi),
            max_nfev=max_nfev,
            x_scale=1.0,
        )
        fitted = layout.candidate(sol.x)
        trial, trial_cost = _line_search(error, fitted, error.cost(fitted), grid, GRID, bounds)
        gain = 1.0 - trial_cost / best_cost if best_cost > 0 else 0.0
        if trial_cost < best_cost:
            best, best_cost = trial, trial_cost
            solution = (
                _Solution(trial, layout, sol.x, sol.jac, sol.fun) if trial is fitted else None
            )
        if gain < RESTART_GAIN:
            break
    return best, best_cost, solution


def _covariance(
    error: _TrainingError,
    best: Candidate,
    bounds: Bounds,
    fixed: Mapping[str, tuple[str, ...]],
    solution: _Solution | None,
) -> ParameterCovariance:
    """The fitted parameters' covariance at ``best``: from the ``solution`` that found it,
    else from a Jacobian taken there (the same two-point difference)."""
    if solution is None or solution.candidate is not best:
        layout = _Layout(best, bounds, fixed, error.force_floor)
        z, lo, hi = layout.start()
        problem = _Problem(error, layout, lo, hi)
        residual = problem.fun(z)
        solution = _Solution(best, layout, z, problem.jac(z), residual)
    layout = solution.layout
    values = [*(float(best.base[k]) for k in BASE_KEYS)]
    values += [float(best.effects[name][pname]) for name, pname, *_ in layout.slots]
    # on the windows' every sample: the noise's lags are true ones across held-out samples,
    # and the noise of the measured velocity each window starts from enters with its gain
    mask = error.training_mask
    jac = np.zeros((mask.size, solution.jac.shape[1]))
    jac[mask] = solution.jac
    residual = np.zeros(mask.size)
    residual[mask] = solution.residual
    return natural_covariance(
        layout.names(),
        values,
        jac,
        residual,
        error.window_ends,
        layout.dnatural_dz(solution.z),
        {f"{name}.{pname}": (lo, hi) for name, pname, _, lo, hi in layout.slots},
        valid=mask,
        start_gain=error.start_gain(best),
    )


@dataclass(frozen=True)
class _Deferred:
    """:func:`_covariance` of a refit, run when the covariance is first asked for."""

    error: _TrainingError
    best: Candidate
    bounds: Bounds
    fixed: Mapping[str, tuple[str, ...]]
    solution: _Solution | None

    def __call__(self) -> ParameterCovariance:
        return _covariance(self.error, self.best, self.bounds, self.fixed, self.solution)


def with_covariance(data: DiagnosisData, fit: FitResult, like: FitResult) -> FitResult:
    """``fit`` with the covariance of the parameters ``like`` (a refit) fitted, for a candidate
    taken from that refit without a refit of its own (a term dropped from it): a Jacobian at
    its values. ``fit`` itself when it has a covariance or ``like`` none."""
    if fit.covariance is not None or like.covariance is None:
        return fit
    bounds: dict[str, dict[str, tuple[float, float]]] = {}
    for key, (lo, hi) in like.covariance.ranges.items():
        name, pname = key.split(".", 1)
        if pname in fit.candidate.effects.get(name, {}):
            bounds.setdefault(name, {})[pname] = (lo, hi)
    return replace(fit, covariance_of=_Deferred(_TrainingError(data), fit.candidate, bounds, {}, None))


def refit(
    data: DiagnosisData,
    cand: Candidate,
    bounds: Bounds,
    fixed: Mapping[str, tuple[str, ...]] | None = None,
    scan: Mapping[str, tuple[str, ...]] | None = None,
    max_nfev: int = MAX_NFEV,
    floor: float = 0.0,
) -> FitResult:
    """Least-squares refit of the base and every effect parameter on training simulation error.

    Parameters
    ----------
    data : DiagnosisData
    cand : Candidate
        Starting point.
    bounds : mapping
        ``{effect: {parameter: (low, high)}}``; parameters without bounds stay fixed.
    fixed : mapping, optional
        ``{effect: (parameter, ...)}`` searched on :data:`GRID` after the gradient fit.
    scan : mapping, optional
        ``{effect: (parameter, ...)}`` scanned on :data:`COARSE` before the gradient fit
        and on :data:`GRID` after it.
    max_nfev : int
        Cost evaluations of the gradient fit.
    floor : float
        Sensor-noise floor of the gap [%]: a rugged candidate that reaches it is not polished.
    """
    fixed = dict(fixed or {})
    scan = dict(scan or {})
    grid = {k: tuple(fixed.get(k, ())) + tuple(scan.get(k, ())) for k in set(fixed) | set(scan)}
    rugged = any(scan.values())
    error = _TrainingError(data)
    best, best_cost = cand, error.cost(cand)
    plain = None
    if rugged:
        # Rugged surfaces: search the rugged parameters, then the base friction and inertia
        # (searched first, the friction bends to a poor phase of the wells), and keep the
        # gradient fit from the start itself where that ends lower.
        plain = _gradient_fit(error, best, best_cost, bounds, fixed, grid, max_nfev)
        best, best_cost = _line_search(
            error, best, best_cost, {**scan, BASE: BASE_SCAN}, COARSE, bounds, ANGLE_COARSE
        )
    best, best_cost, solution = _gradient_fit(error, best, best_cost, bounds, fixed, grid, max_nfev)
    if plain is not None and plain[1] < best_cost:
        best, best_cost, solution = plain
    if rugged and error.gap_percent(best_cost) > POLISH_ABOVE * floor:
        polished, p_cost = _simplex(best, bounds, fixed, error)
        if p_cost < (1.0 - RESTART_GAIN) * best_cost:
            best, best_cost, solution = _gradient_fit(
                error, polished, p_cost, bounds, fixed, grid, max_nfev
            )
    evaluations = error.evaluations  # of the fit; the covariance's Jacobian is not counted
    return evaluate(data, best, evaluations, _Deferred(error, best, dict(bounds), dict(fixed), solution))
