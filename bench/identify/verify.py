"""Verification by simulation: does the identified model reproduce the measured velocity?

The model is simulated with the exact stick-slip integrator on each run's
logged command, from the run's initial velocity
(:func:`~servobench.bench.identify.dataset.initial_velocity`), and compared
with the measured (or derived) velocity::

    fit_percent = 100 * (1 - ||v - v_sim|| / ||v - mean(v)||)

over all runs together (100 % is a perfect fit, 0 % is no better than the
mean). A window restricts the comparison to held-out samples while the
simulation still runs from the start of each run.
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
    for seg in data.segments:
        dt = data.dt_s if seg.dt_s is None else seg.dt_s
        v_sim = simulate_run(model, seg.u, dt, initial_velocity(seg, noise_std), period, seg.act_offset_s)
        sl = slice(start, stop)
        runs.append(
            RunVerification(seg.run, seg.t, seg.u, seg.v, v_sim, fit_percent(seg.v[sl], v_sim[sl]), seg.u_exc)
        )
        measured.append(seg.v[sl])
        simulated.append(v_sim[sl])
    total = fit_percent(np.concatenate(measured), np.concatenate(simulated))
    return Verification(tuple(runs), total, window)
