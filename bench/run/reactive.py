"""The cyclic engine for loops that choose each command from the sample before it.

The relay probe (:mod:`servobench.bench.run.probe`) and the commissioning
bump test (:mod:`servobench.bench.commission.bump`) cannot hand the runner a
command sequence: each command follows from the feedback before it. A
:class:`ReactiveCycle` gives them the runner's terms one exchange at a time:

* ``pace="real"``: the cyclic thread's real-time footing
  (:func:`servobench.realtime.realtime_thread`, reverted at exit), absolute
  deadlines ``t0 + k dt`` (sleep, then spin), each sample's best instant and
  its uncertainty as :func:`servobench.bench.run.cyclic.stream_realtime` takes
  them (the drive's time stamp; else the bracket the transport narrowed; else
  the exchange's own), rows through a ring to a writer thread, the log's
  ``# clock_source`` and ``# rt_*`` lines, the column ``t_unc`` and the
  cycle's timing in the trailer (``host_jitter_*``, ``missed_cycles``, ...);
* ``pace="fast"`` (a lock-step drive): no waiting; ``t`` is the drive's
  clock where it has one, else the nominal grid ``k dt``.

The log is written as samples arrive and closed by :meth:`ReactiveCycle.finish`
(``complete`` or ``incomplete`` with the reason), which drains the ring first.
"""

from __future__ import annotations

import contextlib
import math
import time
from pathlib import Path
from typing import Any

from servobench.bench.log.io import LogWriter
from servobench.bench.run.cyclic import act_instant, sample_instant, spin_here_s
from servobench.bench.run.ring_writer import RingLogWriter
from servobench.bench.run.runner import LOG_COLUMNS, _trailer, realtime_columns, realtime_header
from servobench.bench.run.timing_stats import CycleClock, CycleTiming
from servobench.clock import SPIN_S, sleep_until
from servobench.drivers.base import Drive, Feedback
from servobench.realtime import realtime_thread

#: Cycles each preallocated block of the cycle's instants holds (a new block beyond).
CLOCK_BLOCK = 4096


class ReactiveCycle:
    """One exchange per :meth:`exchange` call, on the cyclic engine's terms (see the module doc).

    Parameters
    ----------
    drive : Drive
        An open drive.
    dt_s : float
        Cycle period [s].
    pace : {"real", "fast"}
    log_path : path
        The CSV log.
    metadata : mapping
        Its header lines (``fs``, ``drive``, ``experiment``, ...).

    Use as a context manager: entering takes the real-time footing and opens
    the log, leaving reverts the footing (and closes the log as incomplete if
    :meth:`finish` was not called).
    """

    def __init__(
        self, drive: Drive, dt_s: float, pace: str, log_path: str | Path, metadata: dict[str, Any]
    ) -> None:
        self.drive, self.dt, self.pace = drive, dt_s, pace
        self.log_path, self.metadata = Path(log_path), dict(metadata)
        self.realtime = pace == "real"
        self.k = 0
        self.t0 = math.nan
        self.t_first: float | None = None
        self.writer: LogWriter | None = None
        self._sink: LogWriter | RingLogWriter | None = None
        self._stack = contextlib.ExitStack()
        self._clocks: list[CycleClock] = []
        self._by_drive = False
        self._acts = False  # the rows carry t_act
        self._spin_s = SPIN_S

    def __enter__(self) -> ReactiveCycle:
        meta, columns = self.metadata, LOG_COLUMNS
        if self.realtime:
            grant = self._stack.enter_context(realtime_thread(helper_threads=self.drive.io_threads()))
            meta, columns = realtime_header(self.drive, grant, meta), realtime_columns(self.drive)
            self._acts = self.drive.reports_action_instant()
            self._by_drive = self.drive.clock_source() == "drive"
            self._spin_s = spin_here_s()
        try:
            self.writer = LogWriter(self.log_path, meta, columns, flush_every=1)
        except BaseException:
            self._stack.close()
            raise
        self._sink = RingLogWriter(self.writer) if self.realtime else self.writer
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if self.writer is not None and self.writer.status is None:
                reason = "interrupted (Ctrl-C)" if exc_type is KeyboardInterrupt else str(exc or "")
                self.finish("incomplete", reason=reason or (exc_type.__name__ if exc_type else "closed"))
        finally:
            self._stack.close()

    @property
    def rows(self) -> int:
        """Rows logged so far."""
        return self._sink.rows if self._sink is not None else 0

    def exchange(self, run: int, u: float) -> tuple[Feedback, float, float]:
        """One cycle: wait for its deadline (real pace), exchange ``u``, log the row.

        Returns the feedback, the command the drive applied and the sample's
        time ``t`` [s] from the session's first sample, as logged.
        """
        assert self._sink is not None, "use ReactiveCycle as a context manager"
        k = self.k
        if k == 0:  # the deadlines count from the first exchange, after the drive's bring-up
            self.t0 = time.monotonic()
        deadline = self.t0 + k * self.dt
        if self.realtime:
            sleep_until(deadline, self._spin_s)
        start = time.monotonic()
        fb, applied = self.drive.exchange(u)
        end = time.monotonic()
        if self.realtime:
            t_abs, t_unc = sample_instant(fb, start, end, self._by_drive)
        else:
            t_abs, t_unc = (fb.t_s if self.drive.drive_clock else k * self.dt), 0.0
        if self.t_first is None:
            self.t_first = t_abs
        t = t_abs - self.t_first
        row = (run, t, applied, fb.velocity, fb.position, end - self.t0)
        if self._acts:
            self._sink.append(*row, t_unc, act_instant(fb, t))
            self._mark(k, deadline, start, end, t_unc)
            self._clocks[-1].late_samples += fb.t_s > fb.t_act_s
        elif self.realtime:
            self._sink.append(*row, t_unc)
            self._mark(k, deadline, start, end, t_unc)
        else:
            self._sink.append(*row)
        self.k += 1
        return fb, applied, t

    def _mark(self, k: int, deadline: float, start: float, end: float, t_unc: float) -> None:
        i = k % CLOCK_BLOCK
        if i == 0:
            self._clocks.append(CycleClock(CLOCK_BLOCK))
            self._clocks[-1].action_instants = self._acts
        self._clocks[-1].mark(i, deadline, start, end, t_unc)

    def timing(self) -> CycleTiming | None:
        """The host's cycle so far (None at fast pace or before the second cycle)."""
        if not self._clocks or self.k < 2:
            return None
        return CycleTiming.of(self._clocks, self.dt)

    def finish(self, status: str = "complete", reason: str = "", **metadata: object) -> None:
        """Drain the ring and write the trailer: the cycle's timing, the drive's counts, ``metadata``."""
        if self.writer is None or self.writer.status is not None:
            return
        if isinstance(self._sink, RingLogWriter):
            self._sink.close()
        clocks = self._clocks if self.timing() is not None else []
        extra = _trailer(self.drive, [], clocks, self.dt)  # the cycle's timing, the drive's counts
        self.writer.finish(status, reason=reason, samples=self.writer.rows, **extra, **metadata)
