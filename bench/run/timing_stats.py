"""Achieved timing of a streamed run: periods of the host and drive clocks, streamed.

Memory is O(1) in the run length (Welford / Chan updates of the moments).
"""

from __future__ import annotations

import math
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
    ``time.monotonic``]. :meth:`mark` stores one cycle and allocates nothing.
    """

    def __init__(self, cycles: int) -> None:
        self.deadline = np.zeros(cycles)
        self.start = np.zeros(cycles)
        self.end = np.zeros(cycles)
        self.t_unc = np.zeros(cycles)
        self.count = 0

    def mark(self, k: int, deadline: float, start: float, end: float, t_unc: float) -> None:
        self.deadline[k] = deadline
        self.start[k] = start
        self.end[k] = end
        self.t_unc[k] = t_unc
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
