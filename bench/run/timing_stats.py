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
