"""Achieved timing of a streamed run: periods of the host and drive clocks, and the drive's tick.

Memory is O(1) in the run length (Welford / Chan updates of the moments);
:class:`CycleClock` holds a real-time run's per-cycle instants in arrays
allocated before the run.

A drive samples on its own control tick ``T``, asynchronous to the host: a
read returns the state latched at its last tick, stamped with that tick's
instant (CiA 402 0x1013, a Modbus time-stamp register, EtherCAT DC time). Two
reads within one tick return the same stamp (a *repeated* sample), and a tick
may pass unread (a *skipped* tick: the stamp jumps by ``n T``, ``n - 1``
skipped). :func:`estimate_tick_s` reads ``T`` from the stamps and
:class:`DriveTicks` counts both per run, for the log's trailer
(``repeated_samples``, ``skipped_ticks``, ``drive_tick_s``: a log contract).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TimingStats:
    """Achieved timing of one run [s]: mean and std of the period, worst period, on host and drive clocks."""

    run: int
    samples: int
    host_period_mean_s: float
    host_jitter_std_s: float
    host_period_max_s: float
    drive_period_mean_s: float
    drive_jitter_std_s: float

    def as_metadata(self) -> dict[str, float]:
        p = f"run{self.run}_"
        return {
            p + "host_period_mean_s": self.host_period_mean_s,
            p + "host_jitter_std_s": self.host_jitter_std_s,
            p + "host_period_max_s": self.host_period_max_s,
            p + "drive_period_mean_s": self.drive_period_mean_s,
            p + "drive_jitter_std_s": self.drive_jitter_std_s,
        }


class PeriodStats:
    """Mean, population std and maximum of the steps of a time series, streamed (Welford).

    :meth:`add` takes time stamps [s] one at a time (or :meth:`add_block`
    many); memory is O(1) in their number.
    """

    def __init__(self) -> None:
        self.samples = 0
        self._last: float | None = None
        self._n = 0
        self._mean = 0.0
        self._m2 = 0.0
        self._max = -math.inf

    def add(self, t: float) -> None:
        self.samples += 1
        if self._last is not None:
            d = t - self._last
            self._n += 1
            delta = d - self._mean
            self._mean += delta / self._n
            self._m2 += delta * (d - self._mean)
            self._max = max(self._max, d)
        self._last = t

    def add_block(self, t: np.ndarray) -> None:
        """Several time stamps at once (Chan's parallel update of the moments)."""
        t = np.asarray(t, dtype=float)
        if t.size == 0:
            return
        steps = np.diff(t) if self._last is None else np.diff(np.concatenate(([self._last], t)))
        self.samples += t.size
        self._last = float(t[-1])
        if steps.size == 0:
            return
        n_b, mean_b = steps.size, float(steps.mean())
        m2_b = float(((steps - mean_b) ** 2).sum())
        n = self._n + n_b
        delta = mean_b - self._mean
        self._mean += delta * n_b / n
        self._m2 += m2_b + delta * delta * self._n * n_b / n
        self._n = n
        self._max = max(self._max, float(steps.max()))

    @property
    def mean(self) -> float:
        return self._mean if self._n else math.nan

    @property
    def std(self) -> float:
        return math.sqrt(self._m2 / self._n) if self._n else math.nan

    @property
    def max(self) -> float:
        return self._max if self._n else math.nan


class CycleClock:
    """The host's instants of one run's cycles, in arrays allocated before the run.

    For cycle ``k``: its deadline, the host clock just before the request went
    out (``start``) and just after the answer came in (``end``) [s, on
    ``time.monotonic``], and the drive's time stamp of the sample (``stamp``
    [s, drive clock], NaN when not given). :meth:`mark` stores one cycle and
    allocates nothing.
    """

    def __init__(self, cycles: int) -> None:
        self.deadline = np.zeros(cycles)
        self.start = np.zeros(cycles)
        self.end = np.zeros(cycles)
        self.t_unc = np.zeros(cycles)
        self.stamp = np.full(cycles, math.nan)
        self.count = 0
        #: The drive read back the torque that acted over each cycle (``Feedback.applied``: 0x6077).
        self.read_back = False
        #: Rows whose read-back showed the command before acting once more (a frame or RPDO late).
        self.late_commands = 0
        #: The drive said where each command took force (the log's ``t_act``), and how many rows'
        #: commands took it before their sample (a later tick's sample read: the host woke late).
        self.action_instants = False
        self.late_samples = 0

    def mark(
        self, k: int, deadline: float, start: float, end: float, t_unc: float, stamp_s: float = math.nan
    ) -> None:
        self.deadline[k] = deadline
        self.start[k] = start
        self.end[k] = end
        self.t_unc[k] = t_unc
        self.stamp[k] = stamp_s
        self.count = k + 1


@dataclass(frozen=True)
class CycleTiming:
    """How well the host kept its cycle, over one run or several [s].

    Attributes
    ----------
    cycles : int
        Cycles measured.
    jitter_p50_s, jitter_p99_s, jitter_max_s : float
        Median, 99th percentile and largest ``|period - 1/fs|`` of the host's
        request instants (NaN with fewer than two cycles).
    missed_cycles : int
        Cycle slots without an exchange: ``round(period * fs) - 1`` summed over
        the periods longer than one and a half cycles.
    late_cycles : int
        Exchanges whose request left more than half a cycle after its deadline.
    t_unc_p50_s, t_unc_p99_s, t_unc_max_s : float
        The samples' timing uncertainty (half-width of the interval known to
        hold each sample's instant; 0 for a drive time stamp).
    """

    cycles: int
    jitter_p50_s: float
    jitter_p99_s: float
    jitter_max_s: float
    missed_cycles: int
    late_cycles: int
    t_unc_p50_s: float
    t_unc_p99_s: float
    t_unc_max_s: float

    @classmethod
    def of(cls, clocks: list[CycleClock], dt_s: float) -> CycleTiming:
        periods = np.concatenate([np.diff(c.start[: c.count]) for c in clocks] or [np.zeros(0)])
        late = sum(int(np.count_nonzero(c.start[: c.count] - c.deadline[: c.count] > 0.5 * dt_s))
                   for c in clocks)  # fmt: skip
        unc = np.concatenate([c.t_unc[: c.count] for c in clocks] or [np.zeros(0)])
        cycles = sum(c.count for c in clocks)
        if periods.size:
            jitter = np.abs(periods - dt_s)
            p50, p99, pmax = (float(x) for x in np.percentile(jitter, [50, 99, 100]))
            long = periods[periods > 1.5 * dt_s]
            missed = int(np.sum(np.round(long / dt_s) - 1))
        else:
            p50 = p99 = pmax = math.nan
            missed = 0
        if unc.size:
            u50, u99, umax = (float(x) for x in np.percentile(unc, [50, 99, 100]))
        else:
            u50 = u99 = umax = math.nan
        return cls(cycles, p50, p99, pmax, missed, late, u50, u99, umax)

    def as_metadata(self, prefix: str = "") -> dict[str, object]:
        """``host_jitter_p50_s`` ... ``t_unc_max_s`` log lines (``prefix`` e.g. ``run1_``)."""
        p = prefix
        return {
            p + "host_jitter_p50_s": self.jitter_p50_s,
            p + "host_jitter_p99_s": self.jitter_p99_s,
            p + "host_jitter_max_s": self.jitter_max_s,
            p + "missed_cycles": self.missed_cycles,
            p + "late_cycles": self.late_cycles,
            p + "t_unc_p50_s": self.t_unc_p50_s,
            p + "t_unc_p99_s": self.t_unc_p99_s,
            p + "t_unc_max_s": self.t_unc_max_s,
        }


#: Fewest positive stamp steps that can show a drive's tick.
MIN_TICK_STEPS = 4
#: Sub-multiples ``s / k`` of the smallest stamp step ``s`` tried as the tick, ``k`` up to this
#: (a host that never read two neighbouring ticks sees only multiples of the tick).
MAX_TICK_DIVISOR = 16
#: Beyond that, the steps' common grid (:func:`stamp_resolution_s`) is the tick where at least
#: this many steps share a grid of at least GCD_TICK_MIN_S [s] (a 16 kHz tick is 62.5 us).
GCD_TICK_STEPS = 20
GCD_TICK_MIN_S = 1e-5
#: The finest stamp resolution considered [s] (EtherCAT DC time counts nanoseconds).
STAMP_FLOOR_S = 1e-9


def stamp_resolution_s(steps_s: np.ndarray) -> float:
    """The stamps' resolution [s]: the greatest common divisor of positive steps, in whole
    nanoseconds (1 ns for stamps on no coarser grid, e.g. floats of a continuous clock)."""
    ns = np.round(np.asarray(steps_s, dtype=float) / STAMP_FLOOR_S)
    ns = ns[(ns > 0) & (ns < 2.0**62)].astype(np.int64)
    return max(1, int(np.gcd.reduce(ns))) * STAMP_FLOOR_S if ns.size else STAMP_FLOOR_S


def _fit_tick_s(steps_s: np.ndarray, guess_s: float) -> float:
    """Least squares ``steps ~ m T`` with ``m`` the steps rounded to multiples of the tick:
    first on the short steps (``m`` surely right), then on all, rounded again."""
    short = steps_s[steps_s <= 4.0 * steps_s.min()]
    m = np.round(short / guess_s)
    tick = float(np.dot(m, short) / np.dot(m, m))
    for _ in range(2):
        m = np.round(steps_s / tick)
        if np.any(m < 1):
            return math.nan
        tick = float(np.dot(m, steps_s) / np.dot(m, m))
    return tick


def estimate_tick_s(steps_s: np.ndarray, magnitude_s: float = 0.0) -> float:
    """The drive's tick [s] from the steps between consecutive time stamps; NaN when none shows.

    Every positive step must be a whole multiple of one tick within the stamps'
    resolution (:func:`stamp_resolution_s`, capped at a quarter tick) and the
    float rounding of stamps of size ``magnitude_s`` [s]. The tick tried
    first is the smallest positive step, then its sub-multiples up to
    :data:`MAX_TICK_DIVISOR`; each is refined by least squares on all positive
    steps over their rounded multiples (:func:`_fit_tick_s`). A drive that
    stamps at the request instant (steps of the host's jitter, not whole ticks)
    gives NaN. Zero, negative and non-finite steps are left out. The tick
    read is the coarsest grid the steps show: a host that reads every ``n``-th
    tick, never one more or one less, sees a tick ``n`` times the drive's.

    Parameters
    ----------
    steps_s : ndarray
        Differences of consecutive stamps of one clock [s].
    magnitude_s : float
        Largest ``|stamp|`` [s], for the rounding error of the differences.

    Returns
    -------
    float
        The tick [s], or NaN.
    """
    d = np.asarray(steps_s, dtype=float)
    d = d[np.isfinite(d) & (d > 0)]
    if d.size < MIN_TICK_STEPS:
        return math.nan
    rounding = 4.0 * float(np.spacing(max(abs(magnitude_s), float(d.max()))))
    resolution = stamp_resolution_s(d)
    smallest = float(d.min())
    # the steps' common grid, where it is far coarser than any stamp register's step (many steps
    # sharing it is no chance) and finer than the steps: the tick, however many ticks apart the
    # host reads
    if d.size >= GCD_TICK_STEPS and GCD_TICK_MIN_S <= resolution < smallest:
        return resolution
    for k in range(1, MAX_TICK_DIVISOR + 1):
        tick = _fit_tick_s(d, smallest / k)
        if not tick > 0:
            continue
        tolerance = min(1.05 * resolution, 0.25 * tick) + rounding
        if float(np.max(np.abs(d - np.round(d / tick) * tick))) <= tolerance:
            return tick
    return math.nan


@dataclass(frozen=True)
class StampCounts:
    """One run's drive time stamps: rows, repeated samples, skipped ticks."""

    run: int
    rows: int
    repeated_samples: int  #: rows whose stamp equals the row before's
    skipped_ticks: int  #: ticks unread between consecutive distinct stamps (0 without a tick)


@dataclass(frozen=True)
class DriveTicks:
    """The drive's tick read from the stamps of all runs, and the counts of each run.

    Attributes
    ----------
    tick_s : float
        The drive's tick [s] (:func:`estimate_tick_s` on the steps of every run;
        steps across runs are left out), NaN when the stamps show no grid.
    runs : tuple of StampCounts
        Per run; skipped ticks counted with ``tick_s`` (none without it).
    """

    tick_s: float
    runs: tuple[StampCounts, ...]

    @classmethod
    def of(cls, stamps: Sequence[tuple[int, np.ndarray]]) -> DriveTicks | None:
        """From ``(run, stamps [s])`` pairs; NaN stamps (none given) are left out. None when no
        run has a stamp."""
        runs = []
        for run, given in stamps:
            s = np.asarray(given, dtype=float)
            if np.isfinite(s).any():
                runs.append((run, s[np.isfinite(s)]))
        if not runs:
            return None
        steps = [np.diff(s) for _, s in runs]
        magnitude = max(float(np.max(np.abs(s))) for _, s in runs)
        tick = estimate_tick_s(np.concatenate(steps), magnitude)
        counts = []
        for (run, s), d in zip(runs, steps, strict=True):
            skipped = 0
            if math.isfinite(tick):
                m = np.round(d[d > 0] / tick)
                skipped = int(np.sum(m - 1))
            counts.append(StampCounts(run, int(s.size), int(np.count_nonzero(d == 0)), skipped))
        return cls(tick, tuple(counts))

    @property
    def repeated_samples(self) -> int:
        return sum(c.repeated_samples for c in self.runs)

    @property
    def skipped_ticks(self) -> int:
        return sum(c.skipped_ticks for c in self.runs)

    def as_metadata(self, per_run: bool = True) -> dict[str, object]:
        """``repeated_samples``, ``skipped_ticks`` and ``drive_tick_s`` (only when the stamps
        show a tick) over all runs, and ``run<n>_repeated_samples``, ``run<n>_skipped_ticks``."""
        out: dict[str, object] = {}
        if per_run:
            for c in self.runs:
                out[f"run{c.run}_repeated_samples"] = c.repeated_samples
                out[f"run{c.run}_skipped_ticks"] = c.skipped_ticks
        out["repeated_samples"] = self.repeated_samples
        out["skipped_ticks"] = self.skipped_ticks
        if math.isfinite(self.tick_s):
            out["drive_tick_s"] = self.tick_s
        return out
