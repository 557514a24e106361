"""Per-sample sanity of drive feedback before it is logged: finite, drive clock sane, not frozen.

A drive's time stamp (its own clock, ``drive_clock``) is the instant of the
drive's last control tick: the host may read twice within one tick and get
the same stamp and the same feedback (a *repeated* sample, logged as read,
not an error), or read after two ticks. Frozen on a drive clock means that
the stamp stands still for longer than ``still_s`` of host time (the drive
watchdog the URL sets, else :data:`STAMP_STILL_S`); a stamp that goes back is
an error at once. Callers check only while the axis is enabled.
"""

from __future__ import annotations

import math

import numpy as np

from servobench.errors import DriveError

#: Consecutive bit-identical feedback samples (while moving) that mean "feedback frozen".
FROZEN_CYCLES = 100
#: Host time a drive's time stamp may stand still while the axis is enabled [s], where the
#: drive URL sets no watchdog: some fifty ticks of a 1 ms drive, no tick of any real drive.
STAMP_STILL_S = 0.05


class FeedbackCheck:
    """Per-sample sanity of the feedback: finite, a drive clock that neither goes back nor
    stands still, not frozen.

    Drive clock: a stamp equal to the one before is a repeated sample (two
    reads within one tick of the drive): fine, unless the stamp has stood still
    for more than ``still_s`` of host time, which is "feedback frozen". A stamp
    that goes back is an error.

    Frozen feedback: (velocity, position) bit-identical for at least
    ``frozen_cycles`` cycles while the axis must be moving -- the drive reports
    ``v != 0`` and ``|v|`` times the time since the feedback froze is at least
    twice the smallest position step seen in this run (so a coarse encoder
    creeping slowly is not taken for a frozen one), or, when ``breakaway`` is
    known, the command stays at or above it. A repeated sample of a drive
    clock neither counts towards nor resets those cycles (a read repeated is
    not a frozen sensor).

    Parameters
    ----------
    frozen_cycles : int
        Cycles of identical feedback that end the run (0 disables the frozen check).
    breakaway : float or None
        Command magnitude [command units] that surely moves the axis.
    drive_clock : bool
        The time stamps are the drive's own clock: they must not go back, nor stand
        still for longer than ``still_s``.
    dt_s : float
        Cycle period [s].
    still_s : float
        Host time a drive clock's stamp may stand still [s].
    """

    def __init__(
        self, frozen_cycles: int = FROZEN_CYCLES, breakaway: float | None = None,
        drive_clock: bool = False, dt_s: float = 1e-3, still_s: float = STAMP_STILL_S,
    ) -> None:  # fmt: skip
        self.frozen_cycles = int(frozen_cycles)
        self.breakaway = breakaway
        self.drive_clock = drive_clock
        self.dt_s = dt_s
        self.still_s = still_s
        self._prev: tuple[float, float] | None = None
        self._prev_t: float | None = None
        self._since_host = math.nan  # host time the current stamp was first read [s]
        self._same = 0
        self._step = math.inf  # smallest non-zero position step seen [position units]

    def _pushing(self, u: float) -> bool:
        return self.breakaway is not None and abs(u) >= self.breakaway

    def check(
        self, t_s: float, u: float, velocity: float, position: float, t_host_s: float = math.nan
    ) -> None:
        """Check one sample; ``u`` is the command that acted over the cycle before it,
        ``t_host_s`` the host time it was read [s] (NaN: unknown, the stamp may then stand
        still unchecked).

        Raises
        ------
        DriveError
            Non-finite feedback, a drive clock that goes back or stands still too long,
            frozen feedback.
        """
        if not (math.isfinite(velocity) and math.isfinite(position) and math.isfinite(t_s)):
            raise DriveError(
                f"drive returned non-finite feedback (v={velocity!r}, x={position!r}, t={t_s!r})"
            )
        if self.drive_clock and self._prev_t is not None and t_s <= self._prev_t:
            if t_s < self._prev_t:
                raise DriveError(_backwards(t_s, self._prev_t))
            still = t_host_s - self._since_host
            if still > self.still_s:
                raise DriveError(_still(t_s, still, self.still_s))
            return  # a repeated sample: two reads within one tick of the drive
        self._since_host = t_host_s
        if self._prev is not None and position != self._prev[1]:
            self._step = min(self._step, abs(position - self._prev[1]))
        same = (velocity, position) == self._prev and (velocity != 0.0 or self._pushing(u))
        self._same = self._same + 1 if same else 0
        self._prev, self._prev_t = (velocity, position), t_s
        if not self.frozen_cycles or self._same < self.frozen_cycles:
            return
        travel = abs(velocity) * self._same * self.dt_s
        if travel >= 2 * self._step:
            why = (
                f"while the drive reports velocity {velocity:.6g} (that is {travel:.3g} of travel)"
            )
        elif self._pushing(u):
            why = f"while commanding |u| >= breakaway {self.breakaway:g}"
        else:
            return
        raise DriveError(
            f"feedback frozen: position and velocity bit-identical for {self._same} cycles {why}"
        )

    def first_failure(
        self, t_s: np.ndarray, u: np.ndarray, v: np.ndarray, x: np.ndarray,
        t_host_s: np.ndarray | None = None,
    ) -> int:  # fmt: skip
        """Check a block at once; return the index of the first bad sample (``len(v)``: none).

        ``t_host_s``: the host time of each sample [s] (None: unknown). The state
        advances over the good samples; :meth:`check` on the bad one then raises
        with the message.
        """
        n = v.size
        if n == 0:
            return 0
        t_host = np.full(n, math.nan) if t_host_s is None else np.asarray(t_host_s, dtype=float)
        bad = ~(np.isfinite(v) & np.isfinite(x) & np.isfinite(t_s))
        index = np.arange(n)
        repeat = np.zeros(n, bool)
        if self.drive_clock:
            prev_t = math.nan if self._prev_t is None else self._prev_t
            with np.errstate(invalid="ignore"):
                step = np.diff(np.concatenate(([prev_t], t_s)))
                bad |= step < 0
                repeat = step == 0
                first_read = np.maximum.accumulate(np.where(repeat, -1, index))
                since = np.where(first_read >= 0, t_host[np.maximum(first_read, 0)], self._since_host)
                bad |= repeat & (t_host - since > self.still_s)
        # each sample is compared with the last sample before it that is not a repeat
        pv, px = self._prev if self._prev is not None else (math.nan, math.nan)
        fresh_before = np.concatenate(([-1], np.maximum.accumulate(np.where(repeat, -1, index))[:-1]))
        earlier = np.maximum(fresh_before, 0)
        v_before = np.where(fresh_before >= 0, v[earlier], pv)
        x_before = np.where(fresh_before >= 0, x[earlier], px)
        same = (v == v_before) & (x == x_before)
        with np.errstate(invalid="ignore"):
            dx = np.abs(x - x_before)
            steps = np.where((dx > 0) & ~repeat, dx, np.inf)  # NaN and 0 are no steps
        step_x = np.minimum(np.minimum.accumulate(steps), self._step)
        pushing = np.abs(u) >= self.breakaway if self.breakaway is not None else np.zeros(n, bool)
        flag = same & ((v != 0.0) | pushing) & ~repeat
        # a repeated sample neither counts towards the frozen cycles nor resets them
        counted = np.cumsum(flag)
        last_reset = np.maximum.accumulate(np.where(~flag & ~repeat, index, -1))
        run = np.where(
            last_reset >= 0, counted - counted[np.maximum(last_reset, 0)], counted + self._same
        )
        if self.frozen_cycles:
            with np.errstate(invalid="ignore"):
                moved = np.abs(v) * run * self.dt_s >= 2 * step_x
            bad |= (run >= self.frozen_cycles) & (moved | pushing) & ~repeat
        hits = np.flatnonzero(bad)
        stop = int(hits[0]) if hits.size else n
        if stop:
            k = stop - 1
            fresh = np.flatnonzero(~repeat[:stop])
            if fresh.size:
                j = int(fresh[-1])
                self._prev, self._prev_t = (float(v[j]), float(x[j])), float(t_s[j])
                self._since_host = float(t_host[j])
            self._same, self._step = int(run[k]), float(step_x[k])
        return stop


def _backwards(t_s: float, prev_s: float) -> str:
    return (
        f"drive clock went backwards: time stamp {t_s:.10g} s after {prev_s:.10g} s "
        f"({(prev_s - t_s) * 1e3:.6g} ms back)"
    )


def _still(t_s: float, still_s: float, limit_s: float) -> str:
    return (
        f"feedback frozen: the drive clock stood at {t_s:.10g} s for {still_s * 1e3:.0f} ms of host "
        f"time while the axis was enabled (allowed {limit_s * 1e3:g} ms)"
    )
