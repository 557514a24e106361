"""Identify a servo model from a log: the method dispatcher and ``auto`` selection.

Methods
-------
``sidbe``
    SIDBE as published (:mod:`servobench.bench.identify.sidbe`); needs the u1/u2 run
    pair of a periodic excitation.
``joint``
    The friction-aware joint estimator (:mod:`servobench.bench.identify.joint`); any
    log, one run or more, velocity or position only.
``auto``
    Both when SIDBE can run; each is fitted without the last excitation
    period and scored by the simulation fit on that held-out period, the
    better one (ties go to ``joint``, which is unbiased) is refitted on all
    the data. With fewer than three periods the steady-state part is scored
    in-sample. On a single-run log ``auto`` is ``joint``, and says so.

Every result is verified by simulation on the whole log
(:func:`servobench.bench.identify.verify.verify`). A real-time log (one that
states its ``clock_source``) also gets its timing figure
(:func:`servobench.bench.identify.timing.timing_figure`): the host's jitter,
missed cycles and the model error its timing predicts.
"""

from __future__ import annotations

import math
from dataclasses import replace

from servobench.bench.blas_threads import on_one_blas_thread
from servobench.bench.identify.dataset import Dataset, prepare
from servobench.bench.identify.drive_grid import (
    MIN_GAIN,
    NICE_TICKS_S,
    TRIAL_GAIN,
    TRIALS,
    acts_on_grid,
    by_simulation,
    find_drive_grids,
    find_run_grids,
    grid_delay_s,
    on_grid,
    phased_by_placed_pairs,
    refit_kept,
)
from servobench.bench.identify.estimate import MethodEstimate
from servobench.bench.identify.joint import identify_joint
from servobench.bench.identify.motion import require_motion
from servobench.bench.identify.sidbe import identify_sidbe, sidbe_applicable
from servobench.bench.identify.timing import timing_figure
from servobench.bench.identify.verify import verify
from servobench.bench.log.io import ExperimentLog
from servobench.bench.model.servo import DELAY_KEY, IdentificationResult
from servobench.errors import IdentificationError, UsageError

#: Methods :func:`identify` accepts.
METHODS = ("auto", "sidbe", "joint")
#: Held-out fits closer than this [percentage points] count as a tie (joint wins ties).
TIE_PERCENT = 1e-3


@on_one_blas_thread
def identify(
    log: ExperimentLog,
    method: str = "auto",
    *,
    resonance: bool = False,
    velocity_cutoff_hz: float | None = None,
    derivative_method: str = "butter",
) -> IdentificationResult:
    """Identify ``M``, ``B`` and Coulomb friction per direction from a log.

    Parameters
    ----------
    log : ExperimentLog
        From :func:`servobench.bench.log.io.read_log` (or built in memory).
    method : {"auto", "sidbe", "joint"}
    resonance : bool
        Let SIDBE fit the series resonance of the paper's eq. (2)-(3).
    velocity_cutoff_hz : float, optional
        Cut-off of the zero-phase position filter for logs without velocity [Hz].
    derivative_method : {"butter", "savgol"}
        How velocity is derived from position.

    Returns
    -------
    IdentificationResult

    Raises
    ------
    IdentificationError
        The data cannot yield a model (no motion, too short, SIDBE on one run ...).
    UsageError
        Unknown method.
    """
    if method not in METHODS:
        raise UsageError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
    data = prepare(log, velocity_cutoff_hz=velocity_cutoff_hz, derivative_method=derivative_method)
    result = identify_data(data, method, resonance=resonance)
    trial = by_simulation(data)  # grids the simulation judges: each kept by its refit
    grids = find_drive_grids(data, result.model, float(result.std.get("delay_s", 0.0) or 0.0),
                             TRIAL_GAIN if trial else MIN_GAIN)  # fmt: skip
    grids = grids[: (TRIALS if data.min_delay_s < 0 else len(grids)) if trial else 1]
    logged, regrid = data, None
    # behind a command's lead the timing figure's draws decide the reads in doubt by this model's
    # odds: the one the grids' first placement decides them by
    first_model = result.model
    best = None
    tried = []
    for grid in grids:  # the drive's tick located on the host's clock: samples onto it
        moved, merged = on_grid(data, grid, result.model)
        try:
            tried.append((grid, moved, merged, identify_data(moved, method, resonance=resonance)))
        except IdentificationError:
            continue
    tried.sort(key=lambda g: -g[3].fit_percent)
    if trial:  # located again under the models identified on them; kept where their models act on them
        tried[:RELOCATE] = [_relocated(data, *g, method, resonance) for g in tried[:RELOCATE]]
        tried = [g for g in tried if acts_on_grid(g[0], g[3].model.delay_s, g[3].std.get(DELAY_KEY, math.nan))]
        tried.sort(key=lambda g: -g[3].fit_percent)
    for grid, moved, merged, again in tried[:1]:
        if not trial or refit_kept(result.fit_percent, again.fit_percent):
            best = (grid, moved, again, merged)
    placer = None  # the model whose pairs placed the reads near a tick (for the timing figure's draws)
    if best is not None and best[0].lead_s <= 0:
        best, placer = _placed_by_pairs(data, *best, method, resonance)
        if not trial:
            best, placer = _phased_by_pairs(data, best, placer, method, resonance)
    # where the pairs placed the reads, the figure's draws place them by draws from the pairs'
    # posterior: a read they decide keeps its tick, one in doubt moves as often as its odds say.
    # Placed by the grid alone, each read anywhere in its bracket, served Modbus RTU at 50 Hz
    # predicted 0.5-0.8 % for models 0.001-0.03 % off; moved anywhere in its bracket and placed by
    # the pairs again, CANopen and Modbus TCP at a 1 ms tick predicted 0.16-1.25 % for exact models
    # (the moved brackets shifted the delay 0.01-0.05 ms, which the held delay carried into M).
    # Behind a command's lead (ODrive serial) the model that placed the reads draws each read in
    # doubt by its odds under its simulation: placed by the grid alone, seven served logs at ticks
    # of 0.25-2 ms predicted 0.87-10.7 % at two sigma for models 0.00004-0.18 % off.
    placements = None
    grid_tick_s = None  # the tick of a located grid whose commands act whole ticks after their sample
    lead_tick_s = None  # the tick of a located grid behind a command's lead
    free_delay_s = None  # there, the delay the log gives where the estimator leaves it free
    if best is not None:
        grid, moved, again, merged = best
        if grid.lead_s <= 0:
            grid_tick_s = grid.tick_s
            if method != "sidbe":
                moved, again, free_delay_s = _held_on_grid(moved, grid, again, method, resonance)
        else:
            lead_tick_s = grid.tick_s
        held = moved.delay_held_s

        def regrid(d: Dataset) -> Dataset:  # the figure's draws where no pairs placed the reads
            return replace(on_grid(d, grid)[0], delay_held_s=held)

        if placer is not None:

            def placements(d: Dataset, rng) -> Dataset:
                return replace(on_grid(d, grid, placer, pairs=True, rng=rng)[0], delay_held_s=held)

        elif grid.lead_s > 0:  # behind a command's lead: each read in doubt drawn by its odds

            def placements(d: Dataset, rng) -> Dataset:
                return on_grid(d, grid, first_model, rng=rng)[0]

        data, result = moved, replace(again, notes=(*again.notes, grid.note(merged)))
        if free_delay_s is not None:
            ticks = round(held / grid_delay_s(moved, grid))
            result = replace(result, notes=(*result.notes, (
                f"the action delay held there, {ticks} tick{'s' if ticks > 1 else ''} after the sample "
                f"({held * 1e3:.4g} ms; left free the log gives {free_delay_s * 1e3:.4g} ms)")))
    estimate = MethodEstimate(result.model, result.method, result.std, result.estimator, result.noise_std)
    placed_delay = None if lead_tick_s is None else (lambda d: grid_delay_s(d, grid))
    timing = timing_figure(log.metadata, data, estimate, regrid, logged, placements, grid_tick_s, lead_tick_s,
                           placed_delay, free_delay_s)  # fmt: skip
    if timing is None:
        return result
    # the delay's stated sigma holds its timing share too (the draws' spread of the delay)
    return replace(result, timing=timing, std={**result.std, DELAY_KEY: timing.delay_error_s})


#: Grids located once more under the model identified on them: every one (the first search's model
#: may put the right tick's first refit behind a wrong one's).
RELOCATE = len(NICE_TICKS_S)


def _relocated(data: Dataset, grid, moved: Dataset, merged: int, again: IdentificationResult, method: str,
               resonance: bool):  # fmt: skip
    """``(grid, moved, merged, result)``: ``grid``'s tick located once more, by its simulation,
    under the model ``again`` identified on it, kept where that verifies better. The
    constant-delay model the first search ran under is bent: by the delay at a slow rate; by the
    rows' differing delays where each command goes ahead of its query (a served ODrive serial log
    at a 1 ms tick, host stalled up to 130 ms, read run 1's phase 0.1 ms off under it: M 1.18 %
    off, 0.04 % once located again)."""
    model = again.model if grid.lead_s > 0 else replace(again.model, delay_s=grid.tick_s)
    better = find_run_grids(data, model, grid.tick_s, grid.lead_s, TRIAL_GAIN, True)
    if better is None:
        return grid, moved, merged, again
    moved2, merged2 = on_grid(data, better, model)
    try:
        again2 = identify_data(moved2, method, resonance=resonance)
    except IdentificationError:
        return grid, moved, merged, again
    if again2.fit_percent > again.fit_percent:
        return better, moved2, merged2, again2
    return grid, moved, merged, again


def _held_on_grid(moved: Dataset, grid, again: IdentificationResult, method: str,
                  resonance: bool) -> tuple[Dataset, IdentificationResult, float | None]:  # fmt: skip
    """``(moved, result, free_delay_s)``: the log moved onto a located grid without a command lead
    identified again with the delay held at the whole ticks after the sample nearest the delay
    ``again`` found free (:attr:`~servobench.bench.identify.dataset.Dataset.delay_held_s`), and
    that free delay [s]; as given, and None, where that fails.

    One request carrying command and sample, the reads moved onto the drive's ticks leave each
    command acting a whole number of ticks after its sample by construction. Left free, the delay
    trades against M: on served Modbus RTU logs at 50 Hz on a 0.25 ms tick the free delay came out
    0.245-0.305 ms, M up to 0.095 % off; held at the tick, the drive's own record.
    """
    tick_s = grid_delay_s(moved, grid)
    held_s = max(1.0, float(round(again.model.delay_s / tick_s))) * tick_s
    data = replace(moved, delay_held_s=held_s)
    try:
        return data, identify_data(data, method, resonance=resonance), again.model.delay_s
    except IdentificationError:
        return moved, again, None


def _placed_by_pairs(data: Dataset, grid, moved: Dataset, again: IdentificationResult, merged: int, method: str,
                     resonance: bool):  # fmt: skip
    """``((grid, moved, result, merged), placer)`` with the reads whose bracket holds a tick placed
    by the pairs of the model identified on ``grid`` (one request carries command and sample:
    :func:`~servobench.bench.identify.pair_placement.place_by_pairs`), kept where that verifies
    as well (within :data:`TIE_PERCENT`) or better; ``placer``: that model, or None where the
    placement was not kept. On a tie the pairs place the reads as the grid does, and the timing
    figure's draws then come from their posterior: drawn anywhere in its bracket instead, each
    read of a served Modbus RTU log at 50 Hz (brackets of +-1.3 ms on a 1 ms tick) moved the delay
    0.22 ms over the draws, and M predicted 1.92 % at two sigma for a model 0.005 % off."""
    moved2, merged2 = on_grid(data, grid, again.model, pairs=True)
    try:
        again2 = identify_data(moved2, method, resonance=resonance)
    except IdentificationError:
        return (grid, moved, again, merged), None
    if again2.fit_percent > again.fit_percent - TIE_PERCENT:
        return (grid, moved2, again2, merged2), again.model
    return (grid, moved, again, merged), None


def _phased_by_pairs(data: Dataset, best: tuple, placer, method: str, resonance: bool) -> tuple[tuple, object]:
    """``(best, placer)`` as :func:`_placed_by_pairs` returns them, with each run's phase read
    again by the pairs of the model identified on the grid once they place the reads near a tick
    (:func:`~servobench.bench.identify.drive_grid.phased_by_placed_pairs`), kept where the model
    identified there verifies better.

    The grid was located with each read at the tick its logged instant gives; where many
    brackets straddle a tick (a host at the drive's own rate that missed cycles), the phase that
    suits that best is off the drive's. A served Modbus TCP drive at a 1 ms tick, read at 1 kHz by
    a host that missed 300 cycles: run 1's phase read 0.89 ms, the model fitted 98.86 % with
    Coulomb 0.76 % off; read again, 0.93 ms, 99.999 % and within 0.001 %.
    """
    grid, moved, again, merged = best  # grid: find_run_grids's RunGrids, one per run
    model = replace(again.model, delay_s=grid.tick_s)
    better = phased_by_placed_pairs(data, model, grid)
    if better == grid:
        return best, placer
    try:
        moved2, merged2 = on_grid(data, better, model, pairs=True)
        again2 = identify_data(moved2, method, resonance=resonance)
    except IdentificationError:
        return best, placer
    if again2.fit_percent > again.fit_percent:
        return (better, moved2, again2, merged2), model
    return best, placer


def _number(text: str | None) -> float:
    try:
        return float(text) if text else 0.0
    except ValueError:
        return 0.0


@on_one_blas_thread
def identify_data(
    data: Dataset, method: str = "auto", *, resonance: bool = False
) -> IdentificationResult:
    """:func:`identify` on a prepared :class:`~servobench.bench.identify.dataset.Dataset`.

    A log where the axis never moved above the sensor noise is refused
    (:func:`~servobench.bench.identify.motion.require_motion`) before any estimator runs.
    """
    require_motion([s.v for s in data.segments], data.source or "the log")
    frf = None
    validation: dict[str, float] = {}
    if method == "sidbe":
        est = identify_sidbe(data, resonance=resonance)
        selection = "sidbe: requested"
    elif method == "joint":
        est = identify_joint(data)
        selection = "joint: requested"
    elif method == "auto":
        est, selection, validation, frf = _auto(data, resonance)
    else:
        raise UsageError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
    ver = verify(est.model, data, est.noise_std)
    notes = est.notes
    if ver.set_aside:
        # behind a command's lead the output error weighs its samples alike, the stalled left out
        fits = "output-error and verification fits" if data.min_delay_s < 0 and est.estimator.endswith(
            "output-error") else "verification fit"
        notes = (*notes, f"{ver.set_aside} samples read in an exchange the host stalled in (t_unc), or that a "
                 f"command sent in one may have moved, left out of the {fits}")  # fmt: skip
    return IdentificationResult(
        model=est.model,
        method=est.method,
        fit_percent=ver.fit_percent,
        std=dict(est.std),
        selection=selection,
        estimator=est.estimator,
        noise_std=est.noise_std,
        validation=validation,
        notes=notes,
        frf=est.frf if est.frf is not None else frf,
        verification=ver,
        units=data.units,
    )


def _auto(data: Dataset, resonance: bool) -> tuple[MethodEstimate, str, dict[str, float], object]:
    reason = sidbe_applicable(data)
    if reason:
        est = identify_joint(data)
        return est, f"auto: joint, because sidbe cannot run on this log: {reason}", {}, None
    assert data.design is not None
    n = data.design.samples_per_period
    periods = data.periodic_periods()
    if periods >= 3:
        fit_data = data.first_periods(periods - 1)
        window = ((periods - 1) * n, periods * n)
        where = "on the held-out last period"
    else:
        fit_data = data
        window = (n, None)
        where = "in-sample on the steady-state period (too few periods to hold one out)"
    candidates: dict[str, MethodEstimate] = {}
    validation: dict[str, float] = {}
    failures: dict[str, str] = {}
    for name, run in (
        ("sidbe", lambda d: identify_sidbe(d, resonance=resonance, leakage=False)),
        ("joint", identify_joint),
    ):
        try:
            est = run(fit_data)
            score = verify(est.model, data, est.noise_std, window).fit_percent
        except IdentificationError as err:
            failures[name] = str(err)
            continue
        candidates[name] = est
        validation[name] = score
    if not candidates:
        raise IdentificationError("; ".join(f"{k}: {v}" for k, v in failures.items()))
    winner = max(candidates, key=lambda k: validation[k] + (TIE_PERCENT if k == "joint" else 0.0))
    others = [k for k in candidates if k != winner]
    if others:
        loser = others[0]
        why = (
            f"auto: {winner}, validation fit {validation[winner]:.3f} % vs {loser} "
            f"{validation[loser]:.3f} % {where}"
        )
    else:
        failed = next(iter(failures))
        why = f"auto: {winner} (validation fit {validation[winner]:.3f} % {where}); {failed} failed: {failures[failed]}"
    final = candidates[winner]
    if winner == "sidbe":  # on all the data, and with the friction leakage in its sigma
        final = identify_sidbe(data, resonance=resonance)
    elif fit_data is not data:
        final = identify_joint(data, start=final)
    # the measured FRF (for the plot) from the held-out comparison is good enough
    frf = candidates["sidbe"].frf if "sidbe" in candidates else None
    return final, why, validation, frf
