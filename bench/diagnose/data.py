"""The log as the diagnosis sees it: per-run signals, comparison windows, held-out samples.

Velocity comes from the log's ``v`` column, or from its position with a
zero-phase filter when the log has none (:func:`velocity_from_position`).

How the model is compared with the data:

* open loop (default): the model runs over each whole run on the logged
  command from the run's initial state -- a pure simulation;
* closed loop (the log's ``loop`` metadata starts with ``closed``, or a
  ``horizon_s`` is given): a position loop keeps the real axis on its
  reference while an open-loop model on the logged force drifts away, so the
  model is restarted from the measured state every ``horizon_s`` and
  compared over that horizon (a multi-step-ahead prediction).

Held-out samples: every third of ten blocks per run (blocks 2, 5, 8) is kept
out of every fit and decides whether a term pays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from servobench.bench.logio import ExperimentLog
from servobench.errors import IdentificationError, UsageError

#: Prediction horizon of closed-loop logs [s].
DEFAULT_HORIZON_S = 0.5
#: Blocks per run and which of them are held out.
BLOCKS = 10
HELD_OUT_BLOCKS = (2, 5, 8)
#: Most training samples a refit simulates (windowed comparisons subsample windows).
REFIT_MAX_SAMPLES = 8000
#: Fewest samples per run.
MIN_RUN_SAMPLES = 50


def lowpass(signal: np.ndarray, fs_hz: float) -> np.ndarray:
    """The project's zero-phase low-pass (:func:`servobench.bench.identify.derivative.lowpass`) at its default cut-off."""
    from servobench.bench.identify.derivative import default_cutoff_hz
    from servobench.bench.identify.derivative import lowpass as zero_phase

    return zero_phase(signal, fs_hz, default_cutoff_hz(fs_hz))


def velocity_from_position(x: np.ndarray, fs_hz: float) -> np.ndarray:
    """Velocity [units/s] from position [units] (:func:`servobench.bench.identify.derivative.differentiate_position`)."""
    from servobench.bench.identify.derivative import differentiate_position

    return differentiate_position(np.asarray(x, dtype=float), fs_hz).v


@dataclass(frozen=True)
class RunSeries:
    """One run, ready for comparison; arrays of shape ``(n,)``.

    Attributes
    ----------
    run : int
    t, u : ndarray
        Time [s] and applied command [command units].
    v : ndarray
        Measured (or position-derived) velocity [units/s]: what the model is compared with.
    x : ndarray
        Position [units] (integrated from ``v`` when the log has none).
    v_f : ndarray
        Low-passed velocity, used for initial states and screening.
    held_out : ndarray of bool
        Samples kept out of every fit.
    starts : ndarray of int
        Sample indices where the model restarts from the measured state.
    """

    run: int
    t: np.ndarray
    u: np.ndarray
    v: np.ndarray
    x: np.ndarray
    v_f: np.ndarray
    held_out: np.ndarray
    starts: np.ndarray


@dataclass(frozen=True)
class DiagnosisData:
    """All runs of a log plus how they are compared."""

    runs: tuple[RunSeries, ...]
    fs_hz: float
    velocity_derived: bool
    horizon_s: float | None
    source: str = ""
    #: White velocity-sensor noise [units/s] (see :func:`noise_std`).
    sigma_v: float = 0.0

    @property
    def dt_s(self) -> float:
        return 1.0 / self.fs_hz

    @property
    def comparison(self) -> str:
        if self.horizon_s is None:
            return "open-loop simulation of each run from its initial state"
        return f"multi-step prediction restarted from the measured state every {self.horizon_s:g} s"

    def cat(self, name: str) -> np.ndarray:
        return np.concatenate([getattr(r, name) for r in self.runs])


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
    fs = float(log.fs_hz)
    if horizon_s is None and is_closed_loop(log):
        horizon_s = DEFAULT_HORIZON_S
    if horizon_s is not None and not (math.isfinite(horizon_s) and horizon_s > 0):
        raise UsageError(f"horizon must be > 0 s, got {horizon_s}")
    runs = []
    derived = False
    for r in log.runs:
        n = len(r)
        if n < MIN_RUN_SAMPLES:
            raise IdentificationError(
                f"run {r.run} has {n} samples; diagnose needs {MIN_RUN_SAMPLES}"
            )
        if r.v is not None:
            v = np.asarray(r.v, dtype=float)
            v_f = lowpass(v, fs)
        else:
            v = velocity_from_position(r.x, fs)
            v_f = v
            derived = True
        if r.x is not None:
            x = np.asarray(r.x, dtype=float)
        else:
            x = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1])) / fs])
        if not np.std(v) > 0:
            raise IdentificationError(f"run {r.run}: the axis does not move")
        block = np.minimum((np.arange(n) * BLOCKS) // n, BLOCKS - 1)
        held = np.isin(block, HELD_OUT_BLOCKS)
        if horizon_s is None:
            starts = np.array([0])
        else:
            step = max(2, int(round(horizon_s * fs)))
            starts = np.arange(0, n, step)
            # A window that straddles blocks counts where it starts: hold out whole windows.
            held = np.repeat(held[starts], np.diff(np.append(starts, n)))
        runs.append(
            RunSeries(
                r.run, np.asarray(r.t, float), np.asarray(r.u, float), v, x, v_f, held, starts
            )
        )
    data = DiagnosisData(tuple(runs), fs, derived, horizon_s, log.source)
    return replace(data, sigma_v=noise_std(data))


def noise_std(data: DiagnosisData) -> float:
    """Standard deviation of white velocity-sensor noise [units/s], robustly from second
    differences (0 for velocity derived from position, already smooth)."""
    if data.velocity_derived:
        return 0.0
    d2 = np.concatenate([np.diff(r.v, 2) for r in data.runs])
    return float(np.median(np.abs(d2 - np.median(d2)))) / 0.6745 / math.sqrt(6.0)


def initial_velocity(run: RunSeries, k: int, sigma: float = 0.0) -> float:
    """Velocity to start a simulation from at sample ``k``: zero when the axis rests there.

    At rest means within three noise deviations ``sigma`` (or 2% of the velocity's spread).
    """
    v0 = float(run.v_f[k])
    tol = max(3.0 * sigma, 0.02 * float(np.std(run.v_f)))
    return 0.0 if abs(v0) < tol else v0


def noise_floor_percent(data: DiagnosisData) -> float:
    """Gap [%] that white velocity-sensor noise alone leaves."""
    return 100.0 * data.sigma_v / float(np.std(data.cat("v")))
