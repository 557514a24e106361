"""The simulated drive's own control tick (``tick=S``, ``serve-sim --tick S``): grid and record.

A real drive runs its control loop on its own tick, asynchronous to the
host: it samples its feedback and applies a new command only at its ticks.
:class:`~servobench.sim_backend.device.SimulatedDevice` (``clock=real``)
does the same when given a tick ``T > 0`` [s]; this module holds what that
needs apart from the physics:

* :class:`TickGrid` (frozen): the tick instants ``phase_s + k * tick_s / rate``
  on the device's wall clock [s], ``rate`` the drive clock's seconds per
  wall-clock second (1 + its drift); :meth:`TickGrid.index_at` is the last
  tick at or before an instant (an instant within 1e-6 tick before a tick
  counts as on it, as :func:`~servobench.sim_backend.device.clock_counts` does);
* :func:`draw_phase`: the phase, uniform in ``[0, tick_s)``, from the
  plant's ``seed`` when it has one (its own stream, apart from the noise),
  else from the operating system's entropy;
* :func:`tick_from_url`: the ``tick`` key of a ``sim://`` URL (a drive
  property, not a plant parameter; default 0: no tick of its own);
* :func:`drift_from_url`: its ``drift`` key [ppm]: the drive's crystal runs
  that much fast (negative: slow) against the host's clock, so its ticks and
  its time stamps drift against the host's cycle as a real drive's do (quartz
  is within some 10-100 ppm; default 0);
* :class:`TimingRecord`: the drive's record of its timing in O(1) memory,
  for benchmarks and tests (:meth:`TimingRecord.as_dict`): each command
  paired with the first read at or after its arrival, and its effective
  action delay ``action tick instant - sample tick instant`` [s] (the
  plant's own transport delay, the ``delay`` effect, is physics and not
  counted); the same mean over the commands that changed the value in force
  (``mean_change_delay_s``: a command that repeats the one before acts alike
  from either tick, so only a change shows its delay in the axis's motion, and
  a log can tell no other); reads that returned the tick the previous read
  returned; ticks that passed unread between two reads (delays in seconds of the
  wall clock, the host's: a drifting drive's tick is ``tick_s / rate`` there). With ``tick_s == 0`` a command acts
  at its arrival: every delay is 0 and no tick repeats or is skipped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from servobench.errors import DriveConfigError

#: An instant this close before a tick [ticks] is on it (rounding in ``phase + k * tick``).
ON_TICK = 1e-6
#: Extra word of the phase's seed: the phase is drawn from its own stream, not the noise's.
PHASE_STREAM = 0x7469636B  # "tick"


#: Largest drive-clock drift accepted [ppm]: 1 %, an RC oscillator's worst; quartz is 10-100 ppm.
MAX_DRIFT_PPM = 1e4


@dataclass(frozen=True)
class TickGrid:
    """Tick instants ``phase_s + k * tick_s / rate`` [s, the device's wall clock], ``tick_s > 0``.

    ``tick_s`` is the tick on the drive's own clock (its time stamps step by it); ``rate`` that
    clock's seconds per wall-clock second (``1 + drift_ppm * 1e-6``).
    """

    tick_s: float
    phase_s: float
    rate: float = 1.0

    @property
    def period_s(self) -> float:
        """The tick on the wall clock [s]."""
        return self.tick_s / self.rate

    def index_at(self, t_s: float) -> int:
        """Index of the last tick at or before ``t_s`` [s]."""
        return math.floor((t_s - self.phase_s) / self.period_s + ON_TICK)

    def instant(self, k: int) -> float:
        """Instant [s] of tick ``k``."""
        return self.phase_s + k * self.period_s


def draw_phase(tick_s: float, seed: int | None) -> float:
    """A phase uniform in ``[0, tick_s)`` [s]: seeded by ``seed`` (plant's), else random."""
    if not tick_s > 0:
        return 0.0
    rng = np.random.default_rng(None if seed is None else [int(seed), PHASE_STREAM])
    return min(float(rng.uniform(0.0, tick_s)), math.nextafter(tick_s, 0.0))


def check_tick(tick_s: float, where: str = "tick") -> float:
    """``tick_s`` as a float if finite and >= 0, else :class:`DriveConfigError` naming ``where``."""
    value = float(tick_s)
    if not (math.isfinite(value) and value >= 0):
        raise DriveConfigError(f"{where} must be a finite number of seconds >= 0, got {tick_s!r}")
    return value


def check_drift(drift_ppm: float, where: str = "drift") -> float:
    """``drift_ppm`` as a float if finite and within +-:data:`MAX_DRIFT_PPM`, else
    :class:`DriveConfigError` naming ``where``."""
    value = float(drift_ppm)
    if not (math.isfinite(value) and abs(value) <= MAX_DRIFT_PPM):
        raise DriveConfigError(
            f"{where} must be a drift in ppm within +-{MAX_DRIFT_PPM:g}, got {drift_ppm!r}"
        )
    return value


def drift_from_url(url) -> float:
    """The ``drift`` key [ppm] of a parsed ``sim://`` URL (default 0: the host's rate)."""
    if "drift" not in url.query:
        return 0.0
    return check_drift(url.get_float("drift"), f"sim drift={url.query['drift']!r}")


def tick_from_url(url) -> float:
    """The ``tick`` key [s] of a parsed ``sim://`` URL (default 0: no tick of its own)."""
    if "tick" not in url.query:
        return 0.0
    return check_tick(url.get_float("tick"), f"sim tick={url.query['tick']!r}")


class TimingRecord:
    """Running statistics of a drive's timing, O(1) memory (see the module doc).

    Parameters
    ----------
    tick_s, phase_s : float
        The drive's tick [s, its own clock] (0: none) and its phase [s].
    rate : float
        The drive clock's seconds per wall-clock second (1 + its drift): delays are reported in
        wall-clock seconds, ``ticks * tick_s / rate``.
    """

    def __init__(self, tick_s: float = 0.0, phase_s: float = 0.0, rate: float = 1.0) -> None:
        self.tick_s = float(tick_s)
        self.phase_s = float(phase_s)
        self.rate = float(rate)
        self.commands = 0
        self.reads = 0
        self.repeated_reads = 0
        self.skipped_ticks = 0
        self._delay_sum = 0  # [ticks]
        self._delay_min: int | None = None
        self._delay_max: int | None = None
        self._pending: int | None = None  # action tick of the command awaiting its read
        self._pending_value: float | None = None
        self._last_value: float | None = None  # value of the last command paired with a read
        self._last_read: int | None = None  # tick the previous read returned
        self.changes = 0
        self._change_delay_sum = 0  # [ticks]

    def command(self, action_tick: int = 0, value: float | None = None) -> None:
        """A command that takes force at tick ``action_tick`` (tick 0: at its arrival), of
        ``value`` (None: unknown, counted as a change).

        A later command before the next read replaces it (it never acts).
        """
        self._pending = int(action_tick)
        self._pending_value = value

    def read(self, tick: int = 0, counted: bool = True) -> None:
        """A read that returned the sample of tick ``tick`` (tick 0: of its own instant).

        ``counted=False``: another read of a request already counted (a SYNC
        that samples for its position loop and then for its TPDOs); it only
        pairs a command that arrived since.
        """
        if counted:
            self.reads += 1
            if self.tick_s > 0:
                if self._last_read is not None:
                    gap = tick - self._last_read
                    self.repeated_reads += gap == 0
                    self.skipped_ticks += max(0, gap - 1)
                self._last_read = tick
        if self._pending is not None:
            delay = self._pending - tick if self.tick_s > 0 else 0
            self._pending = None
            self.commands += 1
            self._delay_sum += delay
            self._delay_min = delay if self._delay_min is None else min(self._delay_min, delay)
            self._delay_max = delay if self._delay_max is None else max(self._delay_max, delay)
            value = self._pending_value
            if value is None or value != self._last_value:
                self.changes += 1
                self._change_delay_sum += delay
            self._last_value = value

    def exchanges(self, n: int) -> None:
        """``n`` lock-step exchanges at once (a block): ``n`` commands and reads, no delay."""
        if n <= 0:
            return
        self._pending = None
        self.commands += int(n)
        self.changes += int(n)  # values not seen: each counted a change (its delay is 0)
        self._last_value = None
        self.reads += int(n)
        self._delay_min = min(self._delay_min or 0, 0)
        self._delay_max = max(self._delay_max or 0, 0)

    def as_dict(self) -> dict[str, float | int]:
        """``tick_s``, ``phase_s``, ``drift_ppm``, ``commands``, ``mean/min/max_delay_s``,
        ``changes``, ``mean_change_delay_s``, ``reads``, ``repeated_reads``, ``skipped_ticks``
        (delays 0 before the first command; in wall-clock seconds)."""
        n, c = self.commands, self.changes
        wall_tick = self.tick_s / self.rate
        return {
            "tick_s": self.tick_s,
            "phase_s": self.phase_s,
            "drift_ppm": (self.rate - 1.0) * 1e6,
            "commands": n,
            "mean_delay_s": self._delay_sum / n * wall_tick if n else 0.0,
            "changes": c,
            "mean_change_delay_s": self._change_delay_sum / c * wall_tick if c else 0.0,
            "min_delay_s": (self._delay_min or 0) * wall_tick,
            "max_delay_s": (self._delay_max or 0) * wall_tick,
            "reads": self.reads,
            "repeated_reads": self.repeated_reads,
            "skipped_ticks": self.skipped_ticks,
        }
