"""The drive clock's rate against the host's, read from a log's two clocks; stamps onto host seconds.

A drive that stamps its samples (``clock_source = drive``) counts time by
its own crystal, which runs some 10-100 ppm off the host's (an RC
oscillator up to a percent). Identified on the stamps as they are, every
time constant comes out in the drive's seconds: the mass ``M`` that much
off, and the action delay too. A log without stamps is identified on the
host's clock, so the two would disagree by the drift.

The host logs its own instant of each exchange beside the stamp (the
``t_host`` column, the answer's arrival). :func:`drive_rate` fits the stamps
against those instants with a straight line (refitted once without the rows
beyond three median deviations and a stamp step: a host that stalled between
its request and the answer). Its slope is the drive's seconds per host
second. What stands between the two clocks -- the exchange's latency and the
sample's age within the drive's tick -- is not noise: where the host's cycle
is a whole number of ticks, every read of a stretch finds its sample the
same age, and that age slides with the very drift looked for, wrapping once a
tick has slid by. The slope is then known to about one stamp step over the
run, not better, and its 1-sigma says so: the residual's scatter in
quadrature with ``q / (span sqrt(3))``, ``q`` the stamps' typical step.

Stamps that step by exactly one amount from row to row count the host's
exchanges (a lock-step drive's cycle count), they are no clock: no rate is
read from them. A rate beyond :data:`MAX_DRIFT_PPM` is no crystal's either
(:attr:`DriveRate.is_clock`).

:func:`onto_host_seconds` maps each run's stamps to the host's seconds,
``t0 + (t - t0) / rate``, where the drift is significant (beyond
:data:`SIGMAS` sigmas and :data:`MIN_DRIFT_PPM`) and a clock's. Equal stamps
stay equal, so repeated samples are still found.

Pure: arrays in, arrays and a frozen result out; no transport.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Shortest run a rate is read from [host seconds].
MIN_SPAN_S = 1.0
#: Fewest rows with both clocks a rate needs.
MIN_ROWS = 50
#: A drift is taken in when beyond this many of its sigmas ...
SIGMAS = 4.0
#: ... and beyond this [ppm] (below it, a time constant moves by less than 1e-6 of itself).
MIN_DRIFT_PPM = 1.0
#: Drifts beyond this [ppm] are no clock's: the stamps count something else (lock-step cycles).
MAX_DRIFT_PPM = 2e4


@dataclass(frozen=True)
class DriveRate:
    """The drive clock's seconds per host second over one run.

    Attributes
    ----------
    rate : float
        Drive seconds per host second (``1 + drift``).
    rate_std : float
        Its 1-sigma: the line's, with a stamp step over the run in quadrature.
    rows : int
        Rows the line went through.
    """

    rate: float
    rate_std: float
    rows: int

    @property
    def drift_ppm(self) -> float:
        """How fast the drive clock ran against the host's [ppm] (negative: slow)."""
        return (self.rate - 1.0) * 1e6

    @property
    def drift_std_ppm(self) -> float:
        return self.rate_std * 1e6

    @property
    def is_clock(self) -> bool:
        """Within :data:`MAX_DRIFT_PPM` of the host's rate: a crystal's drift, not a count."""
        return abs(self.drift_ppm) <= MAX_DRIFT_PPM

    @property
    def significant(self) -> bool:
        """A drift worth mapping: beyond :data:`SIGMAS` sigmas and :data:`MIN_DRIFT_PPM`, and a
        clock's."""
        drift = abs(self.drift_ppm)
        return self.is_clock and drift > MIN_DRIFT_PPM and drift > SIGMAS * self.drift_std_ppm


def drive_rate(stamps_s: np.ndarray, host_s: np.ndarray) -> DriveRate | None:
    """The drive clock's rate against the host's over one run (see the module doc), or None where
    the run spans under :data:`MIN_SPAN_S`, has fewer than :data:`MIN_ROWS` rows with both
    clocks, or its stamps do not advance or count exchanges (one step throughout).

    ``stamps_s``: the drive's time stamps [s, its clock]; ``host_s``: the host's instant of each
    exchange [s, its clock, any origin]; arrays of one shape, non-decreasing.
    """
    t = np.asarray(stamps_s, dtype=float)
    h = np.asarray(host_s, dtype=float)
    ok = np.isfinite(t) & np.isfinite(h)
    t, h = t[ok], h[ok]
    if t.size < MIN_ROWS or not h[-1] - h[0] >= MIN_SPAN_S:
        return None
    steps = np.diff(t)
    if np.ptp(steps) <= 1e-6 * abs(float(steps[0])):  # one step throughout: a count, no clock
        return None
    steps = steps[steps > 0]
    if steps.size == 0:
        return None
    q = float(np.median(steps))
    x = h - h.mean()
    keep = np.ones(t.size, dtype=bool)
    for _ in range(2):
        slope, icpt = np.polyfit(x[keep], t[keep], 1)
        r = t - (slope * x + icpt)
        centre = float(np.median(r[keep]))
        mad = 1.4826 * float(np.median(np.abs(r[keep] - centre)))
        new = np.abs(r - centre) <= 3.0 * mad + q
        if np.count_nonzero(new) < MIN_ROWS or np.array_equal(new, keep):
            break
        keep = new
    slope, icpt = np.polyfit(x[keep], t[keep], 1)
    r = t[keep] - (slope * x[keep] + icpt)
    n = int(np.count_nonzero(keep))
    xs = x[keep]
    sxx = float(np.sum((xs - xs.mean()) ** 2))
    stat = math.sqrt(float(r @ r) / max(n - 2, 1) / sxx) if sxx > 0 else math.inf
    span = float(xs[-1] - xs[0])
    return DriveRate(float(slope), math.hypot(stat, _quantum_std(q, span)), n)


def quantised_rate_std(t_s: np.ndarray) -> float:
    """The 1-sigma [relative] to which instants that step by whole ticks fix a clock's rate over
    their span: ``q / (span sqrt(3))``, ``q`` their median positive step (0 where they hold fewer
    than two distinct instants). The same bound holds where a log's reads were moved onto a tick
    grid located on the host's clock: a grid whose drift is off by less than a tick over the run
    places every read alike. The reads' spacing, not the grid's tick, is kept as the quantum
    there: the grid's drift is chosen between none and its windows' slope, and a drive 100 ppm
    off over 4 s runs is off by more than a 0.25 ms tick (a wider bound than the tick's: served
    Modbus RTU at 50 Hz on a 1 ms grid, 20 ms steps over 4 s runs, states M 0.29 % for models
    within 0.02 %, still within the stated accuracy at two sigma)."""
    t = np.asarray(t_s, dtype=float)
    steps = np.diff(t)
    steps = steps[steps > 0]
    span = float(t[-1] - t[0]) if t.size else 0.0
    if steps.size == 0 or not span > 0:
        return 0.0
    return _quantum_std(float(np.median(steps)), span)


def _quantum_std(q: float, span: float) -> float:
    """A step ``q`` over ``span``, uniform: ``q / (span sqrt(3))``."""
    return q / (span * math.sqrt(3.0))


def onto_host_seconds(stamps_s: np.ndarray, rate: DriveRate) -> np.ndarray:
    """``stamps_s`` [drive seconds] as host seconds from the run's first stamp: ``t0 + (t - t0) / rate``."""
    t = np.asarray(stamps_s, dtype=float)
    if t.size == 0:
        return t
    return t[0] + (t - t[0]) / rate.rate
