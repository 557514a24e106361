"""The log as the diagnosis compares it: the prepared runs, comparison windows, held-out samples.

The runs are the project's one prepared log
(:class:`~servobench.bench.identify.dataset.Dataset`): velocity from the log's
``v`` column, or from its position with a zero-phase filter when the log has
none. On top of it the diagnosis decides how the model is compared with the
data:

* open loop (default): the model runs over each whole run on the logged
  command from the run's initial state -- a pure simulation;
* closed loop (the log's ``loop`` metadata starts with ``closed``, or a
  ``horizon_s`` is given): a position loop keeps the real axis on its
  reference while an open-loop model on the logged force drifts away, so the
  model is restarted from the measured state every ``horizon_s`` and
  compared over that horizon (a multi-step-ahead prediction).

Held-out samples: every third of ten blocks per run (blocks 2, 5, 8) is kept
out of every fit and decides whether a term pays.

Fitting windows: refits compare on at most :data:`REFIT_MAX_SAMPLES` training
samples. A long open-loop log (a default SIDBE log holds 64,000 samples) is
fitted on windows of :data:`FIT_WINDOW_S` restarted from the measured state,
an evenly spread subset of them, while every gap the diagnosis reports is
still that of the comparison above, over all samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from servobench.bench.identify.dataset import Dataset, Segment
from servobench.bench.identify.dataset import prepare as prepare_log
from servobench.bench.identify.motion import require_motion, second_difference_sigma
from servobench.bench.identify.resolution import signal_step, step_noise_std
from servobench.bench.log.io import ExperimentLog
from servobench.errors import IdentificationError, UsageError
from servobench.units import SignalUnits

#: Prediction horizon of closed-loop logs [s].
DEFAULT_HORIZON_S = 0.5
#: Blocks per run and which of them are held out.
BLOCKS = 10
HELD_OUT_BLOCKS = (2, 5, 8)
#: Most training samples a refit simulates (windowed comparisons subsample windows).
REFIT_MAX_SAMPLES = 8000
#: Length of the fitting windows of long open-loop logs [s].
FIT_WINDOW_S = 2.0
#: Fewest samples per run.
MIN_RUN_SAMPLES = 50


@dataclass(frozen=True)
class DiagnosisData:
    """A prepared log and how the diagnosis compares the model with it.

    Attributes
    ----------
    prepared : Dataset
        The runs (velocity measured or derived, position, command).
    horizon_s : float or None
        Restart horizon [s]; None for whole-run simulation.
    held_out : tuple of ndarray of bool
        Per run, the samples kept out of every fit.
    starts : tuple of ndarray of int
        Per run, the sample indices where the model restarts from the measured state.
    sigma_v : float
        White velocity-sensor noise [units/s] (see :func:`noise_std`).
    fit_starts : tuple of ndarray of int
        Per run, the restarts of the fitting windows (``starts`` unless the log is long).
    units : SignalUnits
        Units of ``u``, ``v`` and ``x`` from the log's metadata.
    """

    prepared: Dataset
    horizon_s: float | None
    held_out: tuple[np.ndarray, ...]
    starts: tuple[np.ndarray, ...]
    sigma_v: float = 0.0
    fit_starts: tuple[np.ndarray, ...] = ()
    units: SignalUnits = field(default_factory=SignalUnits)

    def __post_init__(self) -> None:
        if not self.fit_starts:
            object.__setattr__(self, "fit_starts", self.starts)

    @property
    def segments(self) -> tuple[Segment, ...]:
        return self.prepared.segments

    @property
    def v_step(self) -> float:
        """The step the drive reports velocity in [units/s]; 0 when it shows none or the
        velocity is derived (see :mod:`servobench.bench.identify.resolution`)."""
        return velocity_step(self.prepared)

    @property
    def fs_hz(self) -> float:
        return self.prepared.fs_hz

    @property
    def dt_s(self) -> float:
        return self.prepared.dt_s

    @property
    def source(self) -> str:
        return self.prepared.source

    @property
    def derived(self) -> bool:
        """Velocity derived from position."""
        return self.prepared.derived

    @property
    def notes(self) -> tuple[str, ...]:
        """How the log was prepared, and whether it is complete (:class:`Dataset` notes)."""
        return self.prepared.notes

    @property
    def comparison(self) -> str:
        if self.horizon_s is None:
            return "open-loop simulation of each run from its initial state"
        return f"multi-step prediction restarted from the measured state every {self.horizon_s:g} s"

    def cat(self, name: str) -> np.ndarray:
        return self.prepared.cat(name)


def is_closed_loop(log: ExperimentLog) -> bool:
    return str(log.metadata.get("loop", "")).strip().lower().startswith("closed")


def prepare(log: ExperimentLog, horizon_s: float | None = None) -> DiagnosisData:
    """Turn a log into :class:`DiagnosisData`.

    Parameters
    ----------
    log : ExperimentLog
    horizon_s : float, optional
        Restart horizon [s]; by default :data:`DEFAULT_HORIZON_S` for closed-loop
        logs and none (whole-run simulation) otherwise.

    Raises
    ------
    IdentificationError
        Runs too short or without motion.
    UsageError
        Non-positive horizon.
    """
    if horizon_s is None and is_closed_loop(log):
        horizon_s = DEFAULT_HORIZON_S
    if horizon_s is not None and not (math.isfinite(horizon_s) and horizon_s > 0):
        raise UsageError(f"horizon must be > 0 s, got {horizon_s}")
    prepared = prepare_log(log, min_samples=MIN_RUN_SAMPLES)
    for s in prepared.segments:
        if not np.std(s.v) > 0:
            raise IdentificationError(f"run {s.run}: the axis does not move")
    plans = [_plan(len(s), horizon_s, prepared.fs_hz) for s in prepared.segments]
    held_out = tuple(held for held, _ in plans)
    starts = tuple(start for _, start in plans)
    sigma = noise_std(prepared)
    require_motion([s.v for s in prepared.segments], prepared.source or "the log", noise_std=sigma)
    fit_starts = starts
    if horizon_s is None and sum(len(s) for s in prepared.segments) > REFIT_MAX_SAMPLES:
        step = max(MIN_RUN_SAMPLES, int(round(FIT_WINDOW_S * prepared.fs_hz)))
        fit_starts = tuple(np.arange(0, len(s), step) for s in prepared.segments)
    units = SignalUnits.from_metadata(log.metadata)
    return DiagnosisData(prepared, horizon_s, held_out, starts, sigma, fit_starts, units)


def _plan(n: int, horizon_s: float | None, fs_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Held-out mask and restart indices of a run of ``n`` samples."""
    block = np.minimum((np.arange(n) * BLOCKS) // n, BLOCKS - 1)
    held = np.isin(block, HELD_OUT_BLOCKS)
    if horizon_s is None:
        return held, np.array([0])
    step = max(2, int(round(horizon_s * fs_hz)))
    starts = np.arange(0, n, step)
    # A window that straddles blocks counts where it starts: hold out whole windows.
    return np.repeat(held[starts], np.diff(np.append(starts, n))), starts


def noise_std(prepared: Dataset) -> float:
    """Standard deviation of white velocity-sensor noise [units/s], robustly from second
    differences, together with the rounding of a velocity the drive reports in steps (whole
    rpm: :mod:`servobench.bench.identify.resolution`), which second differences do not see;
    0 for velocity derived from position, already smooth."""
    if prepared.derived:
        return 0.0
    white = second_difference_sigma(np.concatenate([np.diff(s.v, 2) for s in prepared.segments]))
    return math.hypot(white, step_noise_std(velocity_step(prepared)))


def velocity_step(prepared: Dataset) -> float:
    """The step a measured velocity is reported in [units/s] (0: none, or derived)."""
    if prepared.derived:
        return 0.0
    return signal_step(np.concatenate([s.v for s in prepared.segments]))


def noise_floor_percent(data: DiagnosisData) -> float:
    """Gap [%] that white velocity-sensor noise alone leaves."""
    return 100.0 * data.sigma_v / float(np.std(data.cat("v")))
