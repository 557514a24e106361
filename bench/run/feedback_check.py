"""Per-sample sanity of drive feedback before it is logged: finite, clock advancing, not frozen."""

from __future__ import annotations

import math

import numpy as np

from servobench.errors import DriveError

#: Consecutive bit-identical feedback samples (while moving) that mean "feedback frozen".
FROZEN_CYCLES = 100


class FeedbackCheck:
    """Per-sample sanity of the feedback: finite, a drive clock that advances, not frozen.

    Frozen feedback: (velocity, position) bit-identical for at least
    ``frozen_cycles`` cycles while the axis must be moving -- the drive reports
    ``v != 0`` and ``|v|`` times the time since the feedback froze is at least
    twice the smallest position step seen in this run (so a coarse encoder
    creeping slowly is not taken for a frozen one), or, when ``breakaway`` is
    known, the command stays at or above it.

    Parameters
    ----------
    frozen_cycles : int
        Cycles of identical feedback that end the run (0 disables the frozen check).
    breakaway : float or None
        Command magnitude [command units] that surely moves the axis.
    drive_clock : bool
        The time stamps are the drive's own clock: they must increase.
    dt_s : float
        Cycle period [s].
    """

    def __init__(
        self, frozen_cycles: int = FROZEN_CYCLES, breakaway: float | None = None,
        drive_clock: bool = False, dt_s: float = 1e-3,
    ) -> None:  # fmt: skip
        self.frozen_cycles = int(frozen_cycles)
        self.breakaway = breakaway
        self.drive_clock = drive_clock
        self.dt_s = dt_s
        self._prev: tuple[float, float] | None = None
        self._prev_t: float | None = None
        self._same = 0
        self._step = math.inf  # smallest non-zero position step seen [position units]

    def _pushing(self, u: float) -> bool:
        return self.breakaway is not None and abs(u) >= self.breakaway

    def check(self, t_s: float, u: float, velocity: float, position: float) -> None:
        """Check one sample; ``u`` is the command that acted over the cycle before it.

        Raises
        ------
        DriveError
            Non-finite feedback, a drive clock that stands still, frozen feedback.
        """
        if not (math.isfinite(velocity) and math.isfinite(position) and math.isfinite(t_s)):
            raise DriveError(
                f"drive returned non-finite feedback (v={velocity!r}, x={position!r}, t={t_s!r})"
            )
        if self.drive_clock and self._prev_t is not None and not t_s > self._prev_t:
            raise DriveError(
                f"feedback frozen: the drive clock stands at {t_s!r} s (last {self._prev_t!r} s)"
            )
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

    def first_failure(self, t_s: np.ndarray, u: np.ndarray, v: np.ndarray, x: np.ndarray) -> int:
        """Check a block at once; return the index of the first bad sample (``len(v)``: none).

        The state advances over the good samples; :meth:`check` on the bad one
        then raises with the message.
        """
        n = v.size
        if n == 0:
            return 0
        bad = ~(np.isfinite(v) & np.isfinite(x) & np.isfinite(t_s))
        if self.drive_clock and self._prev_t is not None:
            bad |= np.diff(np.concatenate(([self._prev_t], t_s))) <= 0
        elif self.drive_clock:
            bad[1:] |= np.diff(t_s) <= 0
        pv, px = self._prev if self._prev is not None else (math.nan, math.nan)
        x_before = np.concatenate(([px], x[:-1]))
        same = (v == np.concatenate(([pv], v[:-1]))) & (x == x_before)
        with np.errstate(invalid="ignore"):
            dx = np.abs(x - x_before)
            steps = np.where(dx > 0, dx, np.inf)  # NaN and 0 are no steps
        step = np.minimum(np.minimum.accumulate(steps), self._step)
        pushing = np.abs(u) >= self.breakaway if self.breakaway is not None else np.zeros(n, bool)
        flag = same & ((v != 0.0) | pushing)
        index = np.arange(n)
        last_reset = np.maximum.accumulate(np.where(flag, -1, index))
        run = np.where(last_reset >= 0, index - last_reset, index + 1 + self._same)
        if self.frozen_cycles:
            with np.errstate(invalid="ignore"):
                moved = np.abs(v) * run * self.dt_s >= 2 * step
            bad |= (run >= self.frozen_cycles) & (moved | pushing)
        hits = np.flatnonzero(bad)
        stop = int(hits[0]) if hits.size else n
        if stop:
            k = stop - 1
            self._prev, self._prev_t = (float(v[k]), float(x[k])), float(t_s[k])
            self._same, self._step = int(run[k]), float(step[k])
        return stop
