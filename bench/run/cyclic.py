"""The real-time cyclic loop of one run: deadlines, the exchange, each sample's instant.

:func:`stream_realtime` is the body of :func:`servobench.bench.run.runner.stream_runs`
with ``pace="real"``, run by the thread :func:`servobench.realtime.realtime_thread`
prepared: absolute deadlines ``t0 + k/fs`` (sleep, then spin), or none where
the transport times the cycle itself; one exchange; the host clock just
before the request and just after the answer; the sample's best instant and
its uncertainty (the drive's time stamp with 0, else the transport's
narrowed interval, else the exchange's bracket, midpoint and half-width);
the row handed to the log ring, the instants (and the drive's time stamp)
to the run's :class:`~servobench.bench.run.timing_stats.CycleClock`. Nothing
in it formats, writes a file or allocates beyond the row itself.

A drive's stamp equal to the one before (two reads within one tick of the
drive) is logged as read, with its equal ``t``; the run's
:class:`~servobench.bench.run.feedback_check.FeedbackCheck` gets each
sample's host time, to tell such a repeat from a drive clock standing still.

A drive that reads back the torque that acted over each cycle
(``Feedback.applied``: CiA 402 torque actual 0x6077 in the TxPDO, on
EtherCAT and CANopen) has each row wait one cycle for it: where the
read-back lies nearer the command that acted the cycle before than the row's own
(its frame or RPDO missed the SYNC / SYNC0, and the command before acted
once more), the row logs the command that acted and the cycle counts as a
late command (``late_commands`` in the trailer, ``u_read_back`` naming the
source). The read-back decides, it is not logged itself: a real drive's
torque actual is measured, and its noise must not reach ``u``.

A drive that says where each command took force
(:meth:`~servobench.drivers.base.Drive.reports_action_instant`: an EtherCAT
DC-synchronous slave) has each row carry it as ``t_act`` (the row's ``t``
moved back by ``Feedback.t_s - Feedback.t_act_s``): where the host woke a
cycle or more late and read a later SYNC0 event's sample, the row's command
acted from the event before, and the identification takes it from there.
Such rows are counted (``late_samples`` in the trailer).
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from servobench.bench.log.io import LogWriter
from servobench.bench.run.feedback_check import FeedbackCheck
from servobench.bench.run.ring_writer import RingLogWriter
from servobench.bench.run.timing_stats import CycleClock, PeriodStats
from servobench.clock import SPIN_S, sleep_until
from servobench.drivers.base import Drive, Feedback

#: The spin before each deadline at ``SCHED_FIFO`` [s]: a real-time thread wakes within
#: tens of microseconds (no timer slack at that policy), so it need not spin the half cycle a
#: time-shared one does (which, at real-time priority, would take half a CPU from every other
#: process). Measured at 1 kHz over 10 s, idle and beside two busy processes: 50 us keeps the
#: request instants' jitter p99 (0.04-0.10 ms) and the missed cycles of 200 us, and takes 11-13 %
#: of a core where 200 us took 27-28 %; 20 us begins to miss deadlines.
RT_SPIN_S = 5e-5


def spin_here_s() -> float:
    """The spin before a deadline for the calling thread [s]: :data:`RT_SPIN_S` at
    ``SCHED_FIFO``, else :data:`~servobench.clock.SPIN_S`."""
    return RT_SPIN_S if os.sched_getscheduler(0) == os.SCHED_FIFO else SPIN_S


def sample_instant(fb: Feedback, start: float, end: float, by_drive: bool) -> tuple[float, float]:
    """A sample's best instant and its uncertainty ``(t, t_unc)`` [s]: the drive's time stamp
    (``by_drive``, uncertainty 0); else the bracket the transport narrowed
    (``fb.t_host_s``, ``fb.t_unc_s``); else the midpoint and half-width of the exchange,
    request out at ``start`` to answer in at ``end`` (host clock)."""
    if by_drive:
        return fb.t_s, 0.0
    if fb.t_host_s == fb.t_host_s:  # the transport narrowed it
        return fb.t_host_s, fb.t_unc_s
    return 0.5 * (start + end), 0.5 * (end - start)


def act_instant(fb: Feedback, t: float) -> float:
    """Where the command of the exchange whose sample is logged at ``t`` [s] took force, on the
    clock of ``t``: ``t`` moved back by ``fb.t_s - fb.t_act_s`` where the drive says it acted
    before its sample (``Feedback.t_act_s``), else ``t``."""
    early = fb.t_s - fb.t_act_s
    return t - early if early > 0 else t


@dataclass
class Run:
    """One run being streamed: where its samples go and what watches them."""

    number: int
    writer: LogWriter | RingLogWriter
    check: FeedbackCheck
    progress: Callable[[int, int], None] | None
    done: int  # samples of earlier runs
    total: int  # samples of all runs
    host: PeriodStats = field(default_factory=PeriodStats)
    clock: PeriodStats = field(default_factory=PeriodStats)

    def report(self, done_here: int) -> None:
        if self.progress is not None:
            self.progress(self.done + done_here, self.total)


def stream_realtime(
    drive: Drive, u: np.ndarray, dt: float, paced_by_drive: bool, run: Run, clock: CycleClock,
    source: str,
) -> None:
    """The cyclic loop: absolute deadlines (sleep, then spin), the exchange, its instants.

    Every sample's best instant and uncertainty (see the module docstring);
    ``t`` counts from the run's first sample.
    """
    n = len(u)
    by_drive = source == "drive"
    append, mark, check = run.writer.append, clock.mark, run.check.check
    monotonic = time.monotonic
    every = max(1, n // 200)
    acted = 0.0
    spin_s = spin_here_s()
    t0_host = monotonic()
    t_first = math.nan
    held: list[float] | None = None  # the row before, waiting for the drive's read-back
    acted_before = 0.0  # the command that acted over the cycle before that row's
    acts = drive.reports_action_instant()  # the row's t_act: where its command took force
    clock.action_instants = acts
    for k in range(n):
        deadline = t0_host + k * dt
        if not paced_by_drive:
            sleep_until(deadline, spin_s)
        start = monotonic()
        fb, applied = drive.exchange(u[k])
        end = monotonic()
        t_abs, t_unc = sample_instant(fb, start, end, by_drive)
        check(fb.t_s, acted, fb.velocity, fb.position, end)
        acted = applied
        if k == 0:
            t_first = t_abs
        t = t_abs - t_first
        t_host = end - t0_host
        row = [run.number, t, applied, fb.velocity, fb.position, t_host, t_unc]
        late = fb.t_s > fb.t_act_s  # the command acted before its sample: a later tick's was read
        if acts:
            row.append(act_instant(fb, t))
            clock.late_samples += late
        read_back = fb.applied
        if held is not None:  # the drive read back the torque that acted over the held row's cycle
            sent = held[2]
            # (not where this sample is a later tick's than the one this command acted from: its
            # read-back is that later tick's, the held row's cycle went unread)
            if (read_back == read_back and not late and sent != acted_before
                    and abs(read_back - acted_before) < abs(read_back - sent)):
                held[2] = acted_before  # its frame came late: the command before acted once more
                clock.late_commands += 1
            acted_before = held[2]
            append(*held)
            held = None
        if read_back == read_back:  # a drive that reads back: the row waits one cycle
            held = row
            clock.read_back = True
        else:
            acted_before = applied
            append(*row)
        mark(k, start if paced_by_drive else deadline, start, end, t_unc, fb.t_s)
        run.host.add(t_host)
        run.clock.add(t)
        if k % every == 0:
            run.report(k + 1)
    if held is not None:  # the last row: no cycle after it to read back
        append(*held)
    run.report(n)

