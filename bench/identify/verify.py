"""Verification by simulation: does the identified model reproduce the measured velocity?

The model is simulated with the exact stick-slip integrator on each run's
logged command, from the run's initial velocity
(:func:`~servobench.bench.identify.dataset.initial_velocity`), and compared
with the measured (or derived) velocity::

    fit_percent = 100 * (1 - ||v - v_sim|| / ||v - mean(v)||)

over all runs together (100 % is a perfect fit, 0 % is no better than the
mean). A window restricts the comparison to held-out samples while the
simulation still runs from the start of each run.

A sample whose instant the log knows only within more than a quarter of a
cycle (``t_unc``, a host that stalled mid-exchange) is left out of the score,
as identification left it out (:data:`~servobench.bench.identify.joint.TIMING_REJECT_SHARE`):
where it was read is unknown, so no model can be scored on it. So are the
samples of any exchange the host stalled in (its bracket well beyond the log's
usual, :meth:`~servobench.bench.identify.dataset.Segment.stalled_rows`) and
those a command change sent in one may have moved (where it acted is unknown:
:meth:`~servobench.bench.identify.dataset.Segment.after_stalled_commands`).
They are counted (:attr:`Verification.set_aside`); where they would be most
of the log, every sample is scored.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from servobench.bench.identify.dataset import Dataset, initial_velocity
from servobench.bench.identify.simulation import simulate_run
from servobench.bench.model.servo import ServoModel, fit_percent


@dataclass(frozen=True)
class RunVerification:
    """One run: times [s], command, measured and simulated velocity (shape ``(n,)``), fit [%];
    in closed loop also the excitation ``u_exc`` (``u`` is then the total command)."""

    run: int
    t: np.ndarray
    u: np.ndarray
    v: np.ndarray
    v_sim: np.ndarray
    fit_percent: float
    u_exc: np.ndarray | None = None


@dataclass(frozen=True)
class Verification:
    """Per-run comparison and the overall fit [%] (over the window, all runs together)."""

    runs: tuple[RunVerification, ...]
    fit_percent: float
    window: tuple[int, int | None] = (0, None)
    #: Samples left out of the score: read in a stalled exchange, or moved by a command sent in one.
    set_aside: int = 0


def verify(
    model: ServoModel,
    data: Dataset,
    noise_std: float = 0.0,
    window: tuple[int, int | None] = (0, None),
) -> Verification:
    """Simulate ``model`` on every run of ``data`` and score the velocity fit.

    Parameters
    ----------
    model : ServoModel
    data : Dataset
    noise_std : float
        Velocity noise [units/s], to decide whether a run starts at rest.
    window : (start, stop)
        Sample range of each run that is scored (simulation always starts at 0).
    """
    period = data.design.samples_per_period if data.design is not None else 0
    runs = []
    measured, simulated = [], []
    start, stop = window
    known = _instant_known(data, model)
    for seg, ok in zip(data.segments, known, strict=True):
        dt = data.dt_s if seg.dt_s is None else seg.dt_s
        v_sim = simulate_run(model, seg.u, dt, initial_velocity(seg, noise_std), period, seg.act_offset_s)
        sl = slice(start, stop)
        keep = ok[sl]
        runs.append(RunVerification(seg.run, seg.t, seg.u, seg.v, v_sim,
                                    fit_percent(seg.v[sl][keep], v_sim[sl][keep]), seg.u_exc))  # fmt: skip
        measured.append(seg.v[sl][keep])
        simulated.append(v_sim[sl][keep])
    total = fit_percent(np.concatenate(measured), np.concatenate(simulated))
    aside = int(sum(np.count_nonzero(~ok[slice(start, stop)]) for ok in known))
    return Verification(tuple(runs), total, window, aside)


def _instant_known(data: Dataset, model: ServoModel) -> list[np.ndarray]:
    """Per run, the samples whose instants are known within a quarter cycle, read in no exchange
    the host stalled in (:meth:`~servobench.bench.identify.dataset.Segment.stalled_rows`), and that
    no command sent in one may have moved (:meth:`~servobench.bench.identify.dataset.Segment.after_stalled_commands`
    under ``model``); all, where that would leave fewer than half of them, as
    identification does."""
    from servobench.bench.identify.joint import MIN_KEPT_SHARE, TIMING_REJECT_SHARE

    known = [np.ones(len(s), dtype=bool) if s.t_unc is None
             else (np.asarray(s.t_unc) / np.sqrt(3.0) <= TIMING_REJECT_SHARE * data.dt_s)
             & ~s.stalled_samples(data.dt_s, model.M, model.B)
             for s in data.segments]  # fmt: skip
    total = sum(k.size for k in known)
    if sum(np.count_nonzero(k) for k in known) < MIN_KEPT_SHARE * total:
        return [np.ones_like(k) for k in known]
    return known
