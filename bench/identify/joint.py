"""The friction-aware joint estimator: ``M``, ``B`` and Coulomb friction per direction at once.

Works on any log -- one run or two, any excitation, open or closed loop:

1. Exact sampled-data regression (:mod:`servobench.bench.identify.regression`) on the sample
   pairs that keep one strict velocity sign. For noise-free data at exact
   instants this is exact at every amplitude and the estimate is final.
   Not so when the instants are uncertain (``t_unc``): the timing weights
   leave the pairs of the transients -- the ones that carry ``M`` -- next
   to no weight, so a vanishing residual says only that the steady pairs
   fit, and ``M`` can be far off (a 10 ms time constant on a 20 ms cycle:
   -58 %). Such logs always go on to steps 2 and 3, whose output error
   weighs each sample equally.
2. With sensor noise (judged from the regression residual): the pairs are
   re-chosen on the simulated, noise-free velocity of the current estimate
   (so the choice does not depend on the noise) and solved by instrumental
   variables with the simulated velocity as instrument, then
3. refined by output-error minimisation on the exact simulator
   (:mod:`servobench.bench.identify.output_error`) -- on the averaged steady-state period of
   periodic logs, or on a window of raw samples otherwise.

Closed-loop logs (a hold loop kept the axis inside its travel; ``u`` is the
total command, ``u_exc`` the excitation): the hold loop feeds the measured,
noisy motion back into ``u``, so ``u`` is correlated with the equation error
and least squares is biased. The instrumental-variable passes then take the
excitation ``u_exc`` as the instrument of ``u`` (and, as in open loop, the
model's simulated velocity, which depends on past commands only, as that of
``v``). The output-error refinement simulates the measured total command on
raw samples, never on averaged periods: the command is not periodic (the
loop adds noise to it) and averaging would mix the noise of ``u`` into the
model. With white velocity noise its residual at the true parameters is
that noise, uncorrelated with the simulation driven by past commands, so
it stays unbiased in closed loop.

Logs with position only go to the inverse-dynamic estimator
(:mod:`servobench.bench.identify.idim`).

Uncertain instants (a real-time log without drive time stamps: the column
``t_unc``, each instant known within ``t +- t_unc``): an interval known to
``sigma_dt`` puts the acceleration times its error into the pair's equation
error, so once a first estimate gives the acceleration the pairs are
weighted by ``1 / (sigma_v^2 (1 + a^2) + (acc sigma_dt)^2)``
(:func:`~servobench.bench.identify.regression.timing_weights`), and pairs
whose interval is uncertain by more than :data:`TIMING_REJECT_SHARE` of the
nominal cycle are set aside. The output-error refinement sets aside the
same samples and weights the others by the share of their variance that is
velocity noise, the rest being the timing errors of the intervals before
them as far as the plant remembers them (:func:`_sample_weights`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from servobench.bench.identify.dataset import MIN_SWITCH_PAIRS, Dataset, Segment, initial_velocity
from servobench.bench.identify.delay import effective_command
from servobench.bench.identify.estimate import MethodEstimate
from servobench.bench.identify.frequency import steady_average
from servobench.bench.identify.idim import identify_idim
from servobench.bench.identify.output_error import (
    MAX_RAW_SAMPLES,
    Chunk,
    measured_chunk,
    refine,
    simulate_chunk,
)
from servobench.bench.identify.regression import (
    Pairs,
    ZohFit,
    fit_pairs,
    fit_pairs_irregular,
    interval_sigma,
    noise_std_from_residual,
    select_pairs,
    timing_weights,
)
from servobench.bench.identify.resolution import grid_step, step_noise_std
from servobench.bench.identify.simulation import simulate_run
from servobench.bench.model.servo import DELAY_KEY, ServoModel
from servobench.errors import IdentificationError

#: Noise below this fraction of the rms velocity counts as none (log rounding is ~1e-10).
EXACT_RTOL = 1e-7
#: Pairs closer to zero velocity than this many noise sigmas are not trusted.
NOISE_SIGMAS = 3.0
#: Instrumental-variable passes.
IV_PASSES = 2
#: Fewest samples (as a fraction) that must move clearly above the noise.
MIN_MOVING_FRACTION = 0.01
#: From this many steady-state periods on, the transient period is left out of the
#: output-error refinement (it adds little information and costs a period of simulation).
MANY_PERIODS = 8
#: Most sample pairs in one regression of noisy data (evenly thinned beyond; the
#: regressions only start the output-error refinement, which sees all the data).
MAX_PAIRS = 100_000
#: Pairs (and output-error samples) whose interval is uncertain by more than this share
#: of the nominal cycle (1 sigma) are set aside.
TIMING_REJECT_SHARE = 0.25
#: Setting aside stops short of leaving fewer than this share of the pairs (weights only then).
MIN_KEPT_SHARE = 0.5
#: The delay scan's grid step and first reach [cycles], and how far it may reach at most.
DELAY_GRID = 0.25
DELAY_MAX_CYCLES = 4.0
DELAY_LIMIT_CYCLES = 32.0
#: Samples the delay scan solves on (all runs together).
DELAY_SCAN_SAMPLES = 40_000
#: :func:`instant_scatter_s` reads the timing from pairs whose acceleration is at least
#: this share of the log's 99th percentile (the transients).
STEEP_SHARE = 0.1


def identify_joint(
    data: Dataset, *, refine_oe: bool = True, start: MethodEstimate | None = None
) -> MethodEstimate:
    """Identify ``M``, ``B``, ``coulomb_pos``, ``coulomb_neg`` from ``data`` (see module docstring).

    Parameters
    ----------
    data : Dataset
    refine_oe : bool
        Run the output-error refinement when the data are noisy.
    start : MethodEstimate, optional
        A joint estimate of (part of) the same data: its model and noise level
        start the output-error refinement directly (used by ``auto`` to refit
        on all data after the held-out comparison).
    """
    if data.derived:
        return identify_idim(data, refine_oe=refine_oe)
    dt = data.dt_s
    notes: list[str] = list(data.notes)
    if data.timing_uncertain:
        aside = timing_set_aside(data)
        notes.append(
            "sample instants known within t_unc: pairs and samples weighted by their timing "
            "uncertainty times the acceleration"
            + (f"; {aside} intervals uncertain by more than {TIMING_REJECT_SHARE:g} cycle set aside" if aside else "")
        )
    v_all = data.cat("v")

    if start is not None and start.estimator.endswith("output-error") and refine_oe:
        sigma = start.noise_std
        return _refine(data, start.model, sigma, NOISE_SIGMAS * sigma, v_all, notes)

    fit = _solve(_pairs(data), data, None)
    if data.delay_held_s is not None:  # the located grid's whole ticks: no scan
        delay_s, delay_std, blind = data.delay_held_s, 0.0, False
        held = delayed(data, delay_s, fit.M / fit.B)
        fit = _solve(_pairs(held), held, fit)
    else:
        delay_s, fit, delay_std = scan_delay(data, fit, data.min_delay_s)
        blind = data.switch_pairs() < MIN_SWITCH_PAIRS
    if blind or (math.isnan(delay_std) and any(s.act_offset_s is not None for s in data.segments)):
        # the pairs cannot tell the delay: no pair holds a command switch (every switch reversed
        # the axis within its interval), so the scan's minimum is the noise's (a jittered serial
        # log once took 0.9 cycles there, and the mass collapsed); or there is no curvature and
        # the commands act each at its own offset (a located grid behind a command lead). The
        # simulation tells it; the output-error refinement gives its sigma.
        scanned, delay_s = delay_s, _delay_by_simulation(data, _model(fit, delay_s)).delay_s
        delay_std = math.nan if blind and delay_s != scanned else delay_std
        fit = _solve(_pairs(delayed(data, delay_s, fit.M / fit.B)), delayed(data, delay_s, fit.M / fit.B), fit)
    ddata = delayed(data, delay_s, fit.M / fit.B)
    sigma = noise_std_from_residual(fit.residual, fit.theta[0])
    v_rms = math.sqrt(float(np.mean(v_all**2)))
    if sigma <= EXACT_RTOL * v_rms and not data.timing_uncertain:
        model = _model(fit, delay_s)
        std = {**fit.physical_std(dt), DELAY_KEY: delay_std}
        if _simulates_exactly(data, model):
            return MethodEstimate(model, "joint", std, "zoh-ls", 0.0, tuple(notes))
        # The pairs hold no command switch (each switch crossed zero within its interval, and
        # such intervals are no pairs): the delay shows only in simulation.
        notes.append("the drive's delay read from the simulation: every switch of the command "
                     "reversed the axis within its interval")  # fmt: skip
        model = _delay_by_simulation(data, model)
        return _refine(data, model, 0.0, 0.0, v_all, notes)

    threshold = NOISE_SIGMAS * sigma
    moving = np.mean(np.abs(v_all) > 2 * threshold)
    if moving < MIN_MOVING_FRACTION:
        raise IdentificationError(
            f"no motion above the sensor noise (sigma {sigma:.3g}); raise the amplitude"
        )
    fit = _solve(_pairs(ddata, threshold), ddata, fit)
    fit, model = _instrumental(data, fit, sigma, v_rms, delay_s)
    if not refine_oe:
        std = {**fit.physical_std(dt), DELAY_KEY: delay_std}
        return MethodEstimate(model, "joint", std, "zoh-iv", sigma, tuple(notes))
    return _refine(data, model, sigma, threshold, v_all, notes)


def _simulates_exactly(data: Dataset, model: ServoModel) -> bool:
    """The model's simulation reproduces every run to :data:`EXACT_RTOL` of its rms velocity."""
    sim = [simulate_run(model, s.u, data.dt_s if s.dt_s is None else s.dt_s, float(s.v[0]), _period(data),
                        s.act_offset_s) for s in data.segments]  # fmt: skip
    v = data.cat("v")
    miss = float(np.sqrt(np.mean((v - np.concatenate(sim)) ** 2)))
    return miss <= EXACT_RTOL * float(np.sqrt(np.mean(v**2)))


def _delay_by_simulation(data: Dataset, model: ServoModel) -> ServoModel:
    """``model`` with the delay, over a grid of :data:`DELAY_GRID` cycles from ``data.min_delay_s``
    to :data:`DELAY_MAX_CYCLES`, that simulates the output-error data best (the other parameters
    held): a start for the refinement, which frees them all."""
    chunks, _ = oe_chunks(data, 0.0)
    lowest = min(0.0, data.min_delay_s / data.dt_s)
    best, best_cost = model, math.inf
    for cycles in sorted({lowest, *np.arange(0.0, DELAY_MAX_CYCLES + 1e-9, DELAY_GRID)}):
        trial = replace(model, delay_s=cycles * data.dt_s)
        cost = sum(float(np.sum(np.asarray(c.weight) * (simulate_chunk(trial, c) - measured_chunk(c)) ** 2))
                   for c in chunks)  # fmt: skip
        if cost < best_cost:
            best, best_cost = trial, cost
    return best


def delayed(data: Dataset, delay_s: float, tau_s: float) -> Dataset:
    """``data`` with each run's command (and excitation) replaced by the command equivalent,
    per interval, to the commands acting ``delay_s`` [s] after their logged instants
    (:func:`~servobench.bench.identify.delay.effective_command`, for a time constant
    ``tau_s`` [s]): the pair regression of the delayed plant. ``data`` itself at delay 0."""
    if delay_s == 0 and all(s.act_offset_s is None for s in data.segments):
        return data

    def eff(s: Segment, u: np.ndarray | None) -> np.ndarray | None:
        if u is None:
            return None
        dt = data.dt_s if s.dt_s is None else s.dt_s
        return np.concatenate((effective_command(u, dt, delay_s, tau_s, offsets_s=s.act_offset_s), u[-1:]))

    return replace(data, segments=tuple(replace(s, u=eff(s, s.u), u_exc=eff(s, s.u_exc))
                                        for s in data.segments))  # fmt: skip


def scan_delay(data: Dataset, fit: ZohFit, min_delay_s: float = 0.0) -> tuple[float, ZohFit, float]:
    """The drive's action delay that best explains the pairs: ``(delay_s, fit at it, 1-sigma)``.

    The pair regression (:func:`delayed` data) is solved on a grid of
    :data:`DELAY_GRID` cycles from ``min_delay_s`` (0, or a command's lead before its
    sample) to :data:`DELAY_MAX_CYCLES` cycles (further while
    the best lies at the grid's end), the sum of squared pair residuals is
    minimised around the best grid point by bounded scalar search, and the
    time constant the equivalent commands need is taken from the fit at the
    previous best (twice). A delay of 0 is kept unless another explains the
    pairs better by more than rounding: exact delay-free data stay exact. The
    sigma is the curvature's (Gauss-Newton) bound on the residual sum at the
    minimum; the output-error refinement, where it runs, replaces it.
    """
    from scipy.optimize import minimize_scalar

    dt = data.dt_s
    pairs0 = _pairs(data)
    rss0 = float(fit.residual @ fit.residual)
    if len(pairs0) < 16 or rss0 == 0.0:
        return 0.0, fit, 0.0
    scan = _scan_data(data)

    start = (fit.M, fit.B, fit.coulomb_pos, fit.coulomb_neg)

    def rss(cycles: float, tau: float) -> float:
        pairs = _pairs(delayed(scan, cycles * dt, tau))
        try:  # plain least squares: the scan only compares delays
            f = fit_pairs_irregular(pairs, start) if scan.jittered else fit_pairs(pairs, dt)
        except IdentificationError:
            return math.inf
        return float(f.residual @ f.residual)

    tau = fit.M / fit.B
    lowest = min(0.0, min_delay_s / dt)
    grid = sorted({lowest, *np.arange(0.0, DELAY_MAX_CYCLES + 1e-9, DELAY_GRID),
                   *(-np.arange(DELAY_GRID, -lowest, DELAY_GRID))})  # fmt: skip
    costs = [rss(c, tau) for c in grid]
    while int(np.argmin(costs)) == len(grid) - 1 and grid[-1] < DELAY_LIMIT_CYCLES:
        more = list(np.arange(grid[-1] + DELAY_GRID, grid[-1] + DELAY_MAX_CYCLES + 1e-9, DELAY_GRID))
        grid += more
        costs += [rss(c, tau) for c in more]
    best = grid[int(np.argmin(costs))]
    for _ in range(2):
        lo, hi = max(lowest, best - DELAY_GRID), best + DELAY_GRID
        res = minimize_scalar(rss, args=(tau,), bounds=(lo, hi), method="bounded",
                              options={"xatol": 1e-7})  # fmt: skip
        best = float(res.x)
        try:
            trial = _solve(_pairs(delayed(data, best * dt, tau)), delayed(data, best * dt, tau), fit)
        except IdentificationError:
            break
        tau = trial.M / trial.B
    full_rss = rss_at = None
    try:
        at = delayed(data, best * dt, tau)
        fit_d = _solve(_pairs(at), at, fit)
        rss_at = float(fit_d.residual @ fit_d.residual)
    except IdentificationError:
        fit_d = None
    full_rss = rss_at if rss_at is not None else math.inf
    if fit_d is None or not full_rss < rss0 * (1.0 - 1e-9):
        return 0.0, fit, 0.0
    # 1 sigma from the curvature of the residual sum (Gauss-Newton): s^2 / (0.5 d2 RSS / dd2)
    h = max(1e-3, 1e-2 * best)
    curv = (rss(best + h, tau) - 2.0 * rss(best, tau) + rss(best - h, tau)) / h**2
    s2 = full_rss / max(1, len(fit_d.residual) - 5)
    if curv > 0:
        std = math.sqrt(2.0 * s2 / curv) * dt
    else:  # no curvature to read: exact pairs (a residual at rounding) pin the delay, others do not
        exact = s2 <= (EXACT_RTOL * float(np.sqrt(np.mean(data.cat("v") ** 2)))) ** 2
        std = 0.0 if exact else math.nan
    return best * dt, fit_d, std


def _scan_data(data: Dataset) -> Dataset:
    """The data the delay scan solves on: each run's first :data:`DELAY_SCAN_SAMPLES` samples
    (the scan only locates the delay; the final fits see everything)."""
    per_run = max(1, DELAY_SCAN_SAMPLES // len(data.segments))
    if all(len(s) <= per_run for s in data.segments):
        return data
    return replace(data, segments=tuple(s.head(per_run) for s in data.segments))


def pair_residual_ms(data: Dataset, delay_s: float, tau_s: float) -> float:
    """Mean squared residual [units^2/s^2] of the plain pair regression (least squares, no
    weights) of the first :data:`DELAY_SCAN_SAMPLES` samples, the commands acting ``delay_s``
    [s] late (equivalent commands for time constant ``tau_s`` [s]): how well a timing explains
    the data, for comparing timings (:mod:`~servobench.bench.identify.drive_grid`)."""
    scan = delayed(_scan_data(data), delay_s, tau_s)
    pairs = _pairs(scan)
    if scan.jittered:
        start = fit_pairs(pairs, float(np.mean(pairs.dt)))
        fit = fit_pairs_irregular(pairs, (start.M, start.B, start.coulomb_pos, start.coulomb_neg))
    else:
        fit = fit_pairs(pairs, data.dt_s)
    return float(np.mean(fit.residual**2))


def pair_regression(data: Dataset, delay_s: float = 0.0, tau_s: float = 1.0) -> ServoModel:
    """The exact pair regression alone (step 1, timing-weighted where the log gives ``t_unc``),
    for commands acting ``delay_s`` [s] late (equivalent commands for time constant ``tau_s``):
    the cheap estimate :mod:`servobench.bench.identify.timing` re-runs on perturbed instants."""
    at = delayed(data, delay_s, tau_s)
    return _model(_solve(_pairs(at), at, None), delay_s)


def _pairs(
    data: Dataset, threshold: float = 0.0, references: list[np.ndarray] | None = None
) -> Pairs:
    """The regression's sample pairs of every run (see :func:`select_pairs`); in closed loop
    with the excitation as the instrument of ``u`` once there are references."""
    closed = references is not None and _closed(data)
    pairs = select_pairs(
        [s.v for s in data.segments],
        [s.u for s in data.segments],
        [np.full(len(s) - 1, data.dt_s) if s.dt_s is None else s.dt_s for s in data.segments],
        references=references,
        threshold=threshold,
        max_pairs=MAX_PAIRS,
        excitations=[s.u_exc for s in data.segments] if closed else None,
        interval_sigmas=_interval_sigmas(data),
    )
    if pairs.sigma_dt is None:
        return pairs
    keep = pairs.sigma_dt <= TIMING_REJECT_SHARE * data.dt_s
    if keep.all() or np.count_nonzero(keep) < MIN_KEPT_SHARE * len(pairs):
        return pairs  # nothing to set aside, or too much: the weights alone then
    return Pairs(*(None if a is None else a[keep] for a in (
        pairs.v0, pairs.v1, pairs.u, pairs.pos, pairs.neg, pairs.dt, pairs.z0, pairs.zu, pairs.sigma_dt)))  # fmt: skip


def _interval_sigmas(data: Dataset) -> list[np.ndarray] | None:
    """Each run's interval uncertainties [s] when the log gives ``t_unc``, else None."""
    if not data.timing_uncertain:
        return None
    return [np.zeros(len(s) - 1) if s.t_unc is None else interval_sigma(s.t_unc) for s in data.segments]


def timing_set_aside(data: Dataset) -> int:
    """Intervals set aside because their length is known worse than :data:`TIMING_REJECT_SHARE`."""
    sig = _interval_sigmas(data)
    if sig is None:
        return 0
    bad = int(sum(np.count_nonzero(s > TIMING_REJECT_SHARE * data.dt_s) for s in sig))
    return bad if bad <= (1.0 - MIN_KEPT_SHARE) * sum(s.size for s in sig) else 0


def _closed(data: Dataset) -> bool:
    """A closed-loop log that carries its excitation."""
    return bool(data.closed_loop) and data.has_excitation


def _instrumental(
    data: Dataset, fit: ZohFit, sigma: float, v_rms: float, delay_s: float = 0.0
) -> tuple[ZohFit, ServoModel]:
    """:data:`IV_PASSES` instrumental-variable fits, each on the pairs and instruments of
    the previous estimate's simulation; the last fit that gives a model, and that model.

    The instruments need simulations: on long non-periodic logs they run on the
    refinement window (:func:`_iv_data`).
    """
    model = _model(fit, delay_s)
    iv = _iv_data(data)
    iv_v = iv.cat("v")
    for _ in range(IV_PASSES):
        div = delayed(iv, delay_s, model.time_constant_s)
        sims = [
            simulate_run(
                model,
                s.u,
                data.dt_s if s.dt_s is None else s.dt_s,
                initial_velocity(s, sigma),
                _period(iv),
                s.act_offset_s,
            )
            for s in iv.segments
        ]
        mismatch2 = float(np.mean((iv_v - np.concatenate(sims)) ** 2)) - sigma**2
        margin = NOISE_SIGMAS * math.sqrt(max(mismatch2, 0.0)) + 1e-12 * v_rms
        try:
            new = _solve(_pairs(div, margin, sims), div, fit, instrumental=True)
            model = _model(new, delay_s)
        except IdentificationError:
            break
        fit = new
    return fit, model


def _refine(
    data: Dataset,
    model: ServoModel,
    sigma: float,
    threshold: float,
    v_all: np.ndarray,
    notes: list[str],
) -> MethodEstimate:
    chunks, note = oe_chunks(data, sigma, model)
    if note:
        notes.append(note)
    held = data.delay_held_s
    if held is not None:
        model = replace(model, delay_s=held)
    oe = refine(model, chunks, _free(v_all, threshold), free_delay=held is None, min_delay_s=data.min_delay_s)
    # a held delay's own sigma is none: what it may be off by is the timing figure's
    std = oe.std if held is None else {**oe.std, DELAY_KEY: 0.0}
    if oe.colour is not None and oe.colour.coloured:
        notes.append(oe.colour.note("the output-error"))
    estimator = "output-error"
    if _closed(data):
        estimator = "zoh-iv (excitation as instrument) + output-error"
        note = "closed-loop log: instruments from the excitation u_exc, output error on raw samples"
        notes.append(note)
    return MethodEstimate(oe.model, "joint", std, estimator, oe.sigma, tuple(notes))


def _free(v_all: np.ndarray, threshold: float) -> tuple[bool, bool, bool, bool]:
    """Which of M, B and the Coulomb levels the refinement fits: a level only where the axis
    moved that way beyond ``threshold``."""
    return True, True, bool(np.any(v_all > threshold)), bool(np.any(v_all < -threshold))


def equally_weighted(data: Dataset, estimate: MethodEstimate) -> ServoModel | None:
    """``estimate``'s output-error refinement again with its samples weighted equally (those set
    aside apart), from its own model: how far the timing weights (:func:`_sample_weights`) moved
    the model, which the timing figure counts. None where the log's instants are known, the
    estimate is not an output-error one, or the refinement fails."""
    if not _weighs_timing(data):
        return None
    refits = _refit(data, estimate, (estimate.model,), weigh=False, free_delay=True)
    return None if refits is None else refits[0]


def delay_held(
    data: Dataset, estimate: MethodEstimate, delays_s: Sequence[float]
) -> tuple[ServoModel, ...] | None:
    """``estimate``'s output-error refinement again with the delay held at each of ``delays_s`` [s]
    (each at least the log's ``min_delay_s``), the other parameters free, from its own model and
    with its own weights: where the plant's parameters would go if the delay were that far off.
    None where the estimate is not an output-error one, the log's instants are known, or a
    refinement fails."""
    starts = [replace(estimate.model, delay_s=max(d, data.min_delay_s)) for d in delays_s]
    return _refit(data, estimate, starts, weigh=True, free_delay=False)


def _refit(data: Dataset, estimate: MethodEstimate, starts: Sequence[ServoModel], weigh: bool,
           free_delay: bool) -> tuple[ServoModel, ...] | None:  # fmt: skip
    """The output-error refinement of ``estimate`` run again from each of ``starts`` on a log whose
    instants are uncertain, over one set of chunks: its samples weighted by their timing under
    ``estimate``'s model (``weigh``) or equally; None where it does not apply or a run fails."""
    if not data.timing_uncertain or data.derived or not estimate.estimator.endswith("output-error"):
        return None
    chunks, _ = oe_chunks(data, estimate.noise_std, estimate.model if weigh else None)
    free = _free(data.cat("v"), NOISE_SIGMAS * estimate.noise_std)
    try:
        free_delay = free_delay and data.delay_held_s is None
        return tuple(refine(start, chunks, free, free_delay=free_delay, min_delay_s=data.min_delay_s).model
                     for start in starts)  # fmt: skip
    except IdentificationError:
        return None


def _iv_data(data: Dataset) -> Dataset:
    """``data``, or for long non-periodic logs the window the output-error refinement uses."""
    periodic = data.design is not None and not data.jittered and data.periodic_periods() >= 2
    per_run = max(1, MAX_RAW_SAMPLES // len(data.segments))
    if periodic or all(len(s) <= per_run for s in data.segments):
        return data
    return replace(data, segments=tuple(s.head(per_run) for s in data.segments))


def _period(data: Dataset) -> int:
    return data.design.samples_per_period if data.design is not None else 0


def _solve(pairs, data: Dataset, previous: ZohFit | None, instrumental: bool = False) -> ZohFit:
    if not data.jittered:
        return fit_pairs(pairs, data.dt_s, instrumental=instrumental)
    if previous is None:
        previous = fit_pairs(pairs, float(np.mean(pairs.dt)))
    start = (previous.M, previous.B, previous.coulomb_pos, previous.coulomb_neg)
    if pairs.sigma_dt is None:
        return fit_pairs_irregular(pairs, start)
    fit = fit_pairs_irregular(pairs, start)  # unweighted: the accelerations for the weights
    floor = _velocity_floor(data)
    for _ in range(2):
        model = (fit.M, fit.B, fit.coulomb_pos, fit.coulomb_neg)
        sigma_v = max(_velocity_noise(pairs, fit), floor)
        fit = fit_pairs_irregular(pairs, model, timing_weights(pairs, model, sigma_v))
    return fit


def instant_scatter_s(data: Dataset, model: ServoModel) -> float:
    """How far the logged instants of ``data`` really stray from the true ones [s], 1 sigma
    each, from the residuals of ``model``; NaN when the log shows too little to tell.

    ``t_unc`` bounds each instant (the half-width of the host's bracket), but a drive
    that samples at a steady point of a wide bracket strays far less: a constant
    delay moves every instant, and every command with it, alike. What reaches the
    data is the interval error ``d_{k+1} - d_k``: a pair's residual is the
    acceleration at its end times that error (plus the velocity noise). On the pairs
    in a transient (acceleration over :data:`STEEP_SHARE` of its 99th percentile, where
    timing shows most and the small misfit of a steady state does not) the
    interval error is the rms of ``e / acc`` (each clipped to what the brackets
    allow; the rms, not a median: the tails of late answers count), and an
    instant's error that over ``sqrt(2)``. Velocity noise and effects the model lacks
    only make it larger, so it errs on the side of a wider scatter.
    """
    try:
        pairs = _pairs(delayed(data, model.delay_s, model.time_constant_s))
    except IdentificationError:
        return math.nan
    if len(pairs) < 8:
        return math.nan
    acc, e = _pair_residual(pairs, model.M, model.B, model.coulomb_pos, model.coulomb_neg)
    steep = np.abs(acc) >= STEEP_SHARE * np.quantile(np.abs(acc), 0.99)
    steep &= np.abs(acc) > 0
    if np.count_nonzero(steep) < 4:
        return math.nan
    bound = _interval_reach(pairs.sigma_dt[steep], model) if pairs.sigma_dt is not None else math.inf
    interval_error = np.clip(e[steep] / acc[steep], -bound, bound)  # never past the brackets
    return float(np.sqrt(np.mean(interval_error**2)) / math.sqrt(2.0))


def _interval_reach(sigma_dt, model: ServoModel):
    """How far an interval's timing can be off [s], given its 1-sigma ``sigma_dt`` [s]: the two
    half-widths of its brackets, ``sqrt(6) sigma_dt`` (uniform instants), and up to the tick of
    a drive that samples at its own last tick (at most its delay)."""
    return math.sqrt(6.0) * sigma_dt + max(model.delay_s, 0.0)


#: :func:`action_scatter_s` reads the commands' actions at the changes of at least this share of
#: the log's largest command (a binary excitation's switches, not a command's small steps).
CHANGE_SHARE = 0.2
#: Fewest changes :func:`action_scatter_s` reads a scatter from.
MIN_CHANGES = 8


def action_scatter_s(data: Dataset, model: ServoModel) -> float:
    """How far each command's action strays from where ``model`` puts it [s], 1 sigma, from the
    residuals at the command's changes; NaN when the log shows too few changes to tell.

    Where each command travels in a request of its own ahead of its sample (a command lead),
    where it acts strays apart from its row's instant. At each change of the command (at
    least :data:`CHANGE_SHARE` of the largest command, alone in its interval), the interval
    that holds its action under the model is stepped exactly (the stick-slip step: a binary
    excitation's reversal crosses zero inside it), the old command up to the action and the new
    one after it; the residual of the measured velocity at the interval's end over that step's
    sensitivity to the action's instant is how far the action strayed, clipped to what the
    brackets allow. Noise, an effect the model lacks and the sample's own timing only make it
    larger. Reading these intervals' residuals against the acceleration at their end
    (:func:`instant_scatter_s`) takes the action's error for the sample's: served at a 0.125 ms
    tick, three ODrive logs read 0.11-0.12 ms that way and 0.056-0.058 ms here; on logs simulated
    with actions strayed by 20, 60 and 100 us this reads 22, 66 and 106 us.
    """
    from servobench.sim_backend.physics.kernels import stick_slip_step

    M, B, fcp, fcn = model.M, model.B, model.coulomb_pos, model.coulomb_neg
    if not (M > 0 and B > 0):
        return math.nan
    top = max((float(np.max(np.abs(seg.u))) for seg in data.segments if len(seg)), default=0.0)

    def end(v0: float, before: float, after: float, a: float, h: float) -> float:
        mid = stick_slip_step(v0, before, a, M, B, fcp, fcn, fcp, fcn)
        return stick_slip_step(mid, after, h - a, M, B, fcp, fcn, fcp, fcn)

    errors = []
    for seg in data.segments:
        n = len(seg)
        if n < 3:
            continue
        t, u, v = np.asarray(seg.t), np.asarray(seg.u), np.asarray(seg.v)
        act = t + model.delay_s + (0.0 if seg.act_offset_s is None else np.asarray(seg.act_offset_s))
        sigma = None if seg.t_unc is None else interval_sigma(np.asarray(seg.t_unc))
        for j in np.flatnonzero(np.abs(np.diff(u)) >= CHANGE_SHARE * top) + 1:
            i = int(np.searchsorted(t, act[j], side="right")) - 1
            if not (0 <= i < n - 1 and act[j - 1] <= t[i] and (j + 1 >= n or act[j + 1] >= t[i + 1])):
                continue  # another change acts in the same interval
            h, a = t[i + 1] - t[i], act[j] - t[i]
            eps = 0.05 * h
            lo, hi = max(a - eps, 0.0), min(a + eps, h)
            slope = (end(v[i], u[j - 1], u[j], hi, h) - end(v[i], u[j - 1], u[j], lo, h)) / (hi - lo)
            if not slope:
                continue
            error = (v[i + 1] - end(v[i], u[j - 1], u[j], a, h)) / slope
            if sigma is not None:
                bound = _interval_reach(sigma[i], model)
                error = min(max(error, -bound), bound)
            errors.append(error)
    if len(errors) < MIN_CHANGES:
        return math.nan
    return float(np.sqrt(np.mean(np.square(errors))))


def _pair_residual(
    pairs: Pairs, M: float, B: float, coulomb_pos: float, coulomb_neg: float
) -> tuple[np.ndarray, np.ndarray]:
    """Each pair's acceleration at its end [units/s^2] and its residual ``e`` [units/s] under
    the model: ``v1`` against the exact step from ``v0`` over the pair's own interval."""
    force = np.where(pairs.pos, coulomb_pos, 0.0) - np.where(pairs.neg, coulomb_neg, 0.0)
    acc = (pairs.u - force - B * pairs.v1) / M
    decay = np.exp(-B * pairs.dt / M)
    return acc, pairs.v1 - decay * pairs.v0 - (1.0 - decay) / B * (pairs.u - force)


def _velocity_floor(data: Dataset) -> float:
    """The least velocity noise [units/s] the timing weights may assume: the rounding of the
    step the drive reports velocity in (:func:`~servobench.bench.identify.resolution.grid_step`),
    and never below :data:`EXACT_RTOL` of the rms velocity.

    A drive that reports velocity in steps repeats its steady values exactly, so the
    residual of the calm pairs can be far below what one reading is worth (3.6e-10
    against a 1e-6 step, measured). Taken as the noise, it leaves the transient pairs --
    the only ones that carry ``M`` -- a weight of 1e-20 of the steady ones, below what
    the least-squares solve can resolve, and ``M`` drifts (-58 % in two passes).
    """
    v = data.cat("v")
    v_rms = math.sqrt(float(np.mean(v**2)))
    return max(step_noise_std(grid_step(v)), EXACT_RTOL * v_rms)


def _velocity_noise(pairs: Pairs, fit: ZohFit) -> float:
    """Velocity noise [units/s] from the residual of the pairs least touched by timing (the
    quarter with the smallest acceleration times interval uncertainty)."""
    acc, e = _pair_residual(pairs, fit.M, fit.B, fit.coulomb_pos, fit.coulomb_neg)
    exposure = np.abs(acc * pairs.sigma_dt)
    calm = exposure <= np.quantile(exposure, 0.25)
    a = math.exp(-fit.B * float(np.mean(pairs.dt)) / fit.M)
    return noise_std_from_residual(e[calm], a)


def _model(fit: ZohFit, delay_s: float = 0.0) -> ServoModel:
    return ServoModel(fit.M, fit.B, max(fit.coulomb_pos, 0.0), max(fit.coulomb_neg, 0.0),
                      delay_s=delay_s)  # fmt: skip


def oe_chunks(data: Dataset, sigma: float, model: ServoModel | None = None) -> tuple[list[Chunk], str]:
    """The data for the output-error refinement.

    Periodic logs: each run's first period from rest (when it starts at rest and
    has fewer than ``MANY_PERIODS`` steady periods) and the average of its
    steady-state periods; otherwise, and for closed-loop logs (whose total command
    is not periodic), a raw window, its samples weighted by their timing under
    ``model`` where their instants are uncertain (:func:`_sample_weights`).
    """
    design = data.design
    if not data.closed_loop and design is not None and not data.jittered and data.periodic_periods() >= 2:
        n = design.samples_per_period
        chunks = []
        for s in data.segments:
            periods = len(s) // n - 1
            v_bar = steady_average(s.v, n, 1)
            if periods < MANY_PERIODS and initial_velocity(s, sigma) == 0.0:
                # from rest: the transient period as logged, then the averaged steady one
                weight = np.concatenate((np.ones(n), np.full(n, float(periods))))
                chunks.append(
                    Chunk(s.u[: 2 * n], np.concatenate((s.v[:n], v_bar)), data.dt_s, weight=weight)
                )
            else:
                chunks.append(
                    Chunk(s.u[n : 2 * n], v_bar, data.dt_s, periodic=True, weight=float(periods))
                )
        return chunks, ""
    per_run = max(1, MAX_RAW_SAMPLES // len(data.segments))
    note = ""
    chunks = []
    timing = _Timing.of(data, sigma, model)
    for s in data.segments:
        seg = s.head(per_run) if len(s) > per_run else s
        if len(s) > per_run:
            note = f"output-error refinement on the first {per_run} samples of each run"
        v0 = initial_velocity(seg, sigma)
        dt = data.dt_s if seg.dt_s is None else seg.dt_s
        weight = _sample_weights(seg, data.dt_s, timing)
        if data.min_delay_s < 0:  # behind a command's lead the samples weigh alike: the stalled set aside
            weight = _unstalled(seg, data.dt_s, model, weight)
        chunks.append(Chunk(seg.u, seg.v, dt, v0, weight=weight, act_offset_s=seg.act_offset_s))
    return chunks, note


def _weighs_timing(data: Dataset) -> bool:
    """The output-error samples are weighted by their timing (:func:`_sample_weights`): a log
    whose instants are uncertain and whose rows each carry command and sample in one request.
    Where each command goes ahead of its sample in a request of its own (ODrive serial: a
    command lead), the rows' delays spread apart from their instants' scatter, which the
    weights do not model: served at a 0.25 ms tick, one log went from 0.48 % to 1.69 % off
    with them (seven others gained), so such logs keep equal weights."""
    return data.timing_uncertain and data.min_delay_s >= 0


def _unstalled(seg, dt_s: float, model: ServoModel | None, weight: float | np.ndarray = 1.0) -> float | np.ndarray:
    """The samples' output-error ``weight`` (:func:`_sample_weights`), 0 also for those of
    exchanges the host stalled in and those a command sent in one may have moved
    (:meth:`~servobench.bench.identify.dataset.Segment.stalled_samples`, under ``model``), where
    the samples are not weighted by their timing (:func:`_weighs_timing`: a command lead).

    Weighted alike, a served ODrive serial log at a 0.25 ms tick, placed on its grid by the true
    model, left every sample within 8e-5 of it at the 99th percentile but for the few after
    two stalled exchanges (0.11 and 0.096 off, one bracket +-2.8 ms): they bent M 0.17 % off and
    the delay 0.063 ms from the record. Set aside: M within 0.002 %, the delay 0.031 ms off (0.003
    once its reads kept the model's scale, :func:`.drive_grid._read_scale`), and the eight other
    logs of that case within 0.05 % (one had been 0.35 % off). ``weight`` stays as it is where the
    samples it and this set aside together would leave fewer than :data:`MIN_KEPT_SHARE` of the
    run: one guard over both, as the verification keeps its samples
    (:func:`~servobench.bench.identify.verify.verify`).
    """
    if seg.t_unc is None or model is None or not (model.M > 0 and model.B > 0):
        return weight
    kept = (np.broadcast_to(weight, (len(seg),)) > 0) & ~seg.stalled_samples(dt_s, model.M, model.B)
    return np.where(kept, weight, 0.0) if np.count_nonzero(kept) >= MIN_KEPT_SHARE * kept.size else weight


@dataclass(frozen=True)
class _Timing:
    """What the output-error weights of samples with uncertain instants need: the model whose
    accelerations expose them, the velocity noise [units/s] and the instants' scatter [s]."""

    model: ServoModel
    sigma_v: float
    scatter_s: float

    @classmethod
    def of(cls, data: Dataset, sigma: float, model: ServoModel | None) -> _Timing | None:
        if model is None or not _weighs_timing(data) or not (model.M > 0 and model.B > 0):
            return None
        return cls(model, max(sigma, _velocity_floor(data)), instant_scatter_s(data, model))


def _sample_weights(seg, dt_s: float, timing: _Timing | None) -> float | np.ndarray:
    """Output-error weight of each raw sample whose instant is uncertain (``t_unc``): 0 for
    samples known worse than :data:`TIMING_REJECT_SHARE` of the cycle (set aside), else the
    share of the sample's variance that is velocity noise, ``sigma_v^2 / (sigma_v^2 + E_k)``
    (1 where there is no model to weigh them by).

    ``E_k`` is what the timing puts into a simulated sample: each interval's error
    (``sqrt(2)`` times the instants' scatter, never more than the brackets allow; an exchange
    the host stalled in, :meth:`~servobench.bench.identify.dataset.Segment.stalled_rows`, by its
    own bracket) times the model's acceleration at its end, squared, with what a command sent in
    a stalled exchange puts in (:func:`_command_exposure`), and carried on to the later samples
    decayed as the plant forgets it (``exp(-2 B dt / M)`` per interval), so a sample carries the
    timing of every interval before it, not its own alone. Weighting each sample by its
    local acceleration alone misstates that, and equal weights let the transients' timing
    decide the model: against a served Modbus RTU drive at 50 Hz under two busy processes
    (scatter 0.04 ms at the median, one interval in 140 off by 1.6 ms, its bracket twice
    the others'), equal weights gave M 2.74 % off and the delay 0.73 +- 0.41 ms for
    0.125 ms.
    """
    if seg.t_unc is None:
        return 1.0
    bad = seg.t_unc / math.sqrt(3.0) > TIMING_REJECT_SHARE * dt_s
    aside = bad.any() and np.count_nonzero(~bad) >= MIN_KEPT_SHARE * len(bad)
    kept = np.where(bad, 0.0, 1.0) if aside else 1.0
    if timing is None:
        return kept
    m = timing.model
    uniform = seg.t_unc / math.sqrt(3.0)  # each instant's sigma within its bracket
    scatter = timing.scatter_s
    sigma_t = np.minimum(scatter, uniform) if math.isfinite(scatter) else uniform
    sigma_t = np.where(seg.stalled_rows(dt_s), uniform, sigma_t)  # not the scatter of the typical rows
    u_acting = np.concatenate((seg.u[:1], seg.u[:-1]))  # the command acting as each sample is taken
    force = np.where(seg.v > 0, m.coulomb_pos, 0.0) - np.where(seg.v < 0, m.coulomb_neg, 0.0)
    acc = (u_acting - force - m.B * seg.v) / m.M  # at the measured velocity (when ODrive serial logs
    # were weighted too, the model's own trajectory put one at a 0.25 ms tick 1.1 % off, against 0.004 %)
    dt = np.full(len(seg) - 1, dt_s) if seg.dt_s is None else np.asarray(seg.dt_s)
    exposure = 2.0 * (acc * sigma_t) ** 2
    exposure[1:] += _command_exposure(seg, dt, m)
    exposure = _carried(exposure, np.exp(-2.0 * m.B * dt / m.M))
    return kept * timing.sigma_v**2 / (timing.sigma_v**2 + exposure)


def _command_exposure(seg, dt: np.ndarray, m: ServoModel) -> np.ndarray:
    """What a command change in an exchange the host stalled in puts into the next sample's
    simulation, per interval (shape ``(n - 1,)``).

    A row's bracket wider than the log's median (``t_unc`` beyond its median: the host stalled
    before the request went out or after) leaves its command's instant uncertain by the excess,
    uniform (``excess / sqrt(3)``, 1 sigma); a typical bracket's offset is the delay's. Its change
    of acceleration ``du / M`` times that sigma reaches the next sample decayed over the shortest
    the interval can have been. The row's own sample may be set aside, but its command acts on
    every later one: a served Modbus RTU log at 50 Hz whose host stalled 69 ms in the exchange of
    a switch (bracket +-34 ms) left the four samples after it the only weight the output error saw
    beside its transients', each weighted down by its own timing alone; the refinement bent M
    46 % off and the delay to 7.9 ms to fit them.
    """
    excess = np.maximum(seg.bracket_excess_s(), 0.0)[:-1]
    du = np.diff(seg.u)  # row k's command change against row k-1's, acting over interval k
    du = np.concatenate(([0.0], du))[:-1]
    nearest = np.maximum(dt - excess, 0.0)
    return (du / m.M * excess / math.sqrt(3.0)) ** 2 * np.exp(-2.0 * m.B * nearest / m.M)


def _carried(exposure: np.ndarray, decay: np.ndarray) -> np.ndarray:
    """``E_k = exposure_k + decay_{k-1} E_{k-1}``: each sample's timing variance and what the
    plant still remembers of the earlier ones'."""
    out = np.empty_like(exposure)
    carried = 0.0
    for k, e in enumerate(exposure):
        carried = float(e) + (float(decay[k - 1]) * carried if k else 0.0)
        out[k] = carried
    return out
