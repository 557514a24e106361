"""Stream excitation runs in closed loop: the axis held inside its travel while it is excited.

The counterpart of :func:`~servobench.bench.run.runner.stream_runs` for axes
with limited travel. The excitation ``u_exc`` is added to the hold loop of a
:class:`~servobench.bench.run.travel.ClosedLoopPlan`: the host's loop (any
drive in torque mode; the command of cycle ``k`` uses the feedback of cycle
``k - 1``), or the drive's own (:meth:`~servobench.drivers.base.Drive.hold_position`,
the excitation then goes out as the drive's torque offset).

Sequence: enable; when the axis is away from the held position, move it
there with the host's loop (a smooth ramp of ``x_ref``, with the plan's
model fed forward: ``M a + B v`` and the Coulomb level of the direction, so
that friction does not stall a slow loop); enter the drive's hold if the
plan says so; rest with the hold on; then each run, resting with the hold on
between runs and restarting the loop's integral at each run's start (as the
prediction does); finally leave the hold, stop and disable.

The log has the columns ``run,t,u,v,x,t_host,u_exc,x_ref`` and the metadata
``loop = closed`` with the controller's parameters. ``u`` is the total
command applied over ``[t_k, t_{k+1})``: the drive's read-back
(``Feedback.applied``, which arrives with the next cycle's feedback, so each
row is written one cycle late) where the drive reports one, else the command
the host sent (after the Drive layer's clamping).

Real time (``pace = "real"``): as in open loop, the calling thread takes the
OS's best footing (:func:`servobench.realtime.realtime_thread`, the ``rt_*``
lines), rows go through the ring to a writer thread, each sample gets its
best instant (``# clock_source``) and its uncertainty in the extra last
column ``t_unc``, and the trailer carries the cycle's timing (and, on a
drive clock, ``repeated_samples``, ``skipped_ticks``, ``drive_tick_s``). The
drive that times the cycle itself
(:meth:`~servobench.drivers.base.Drive.start_cycle_clock`: a DC-synchronous
EtherCAT slave, SYNC on SocketCAN) paces it, as in open loop; else the
deadlines ``t0 + k dt`` count from the first cycle after the drive is enabled,
and start again from the cycle after each non-cyclic step (entering the
drive's hold, restarting it between runs); a cycle more than half a period
late starts at once, is counted late against its deadline, and the deadlines
count on from it: a loop never bursts to catch up (a host loop run faster than
its period, a move faster than planned) and never trails the drive's own cycle
for the rest of a session (a DC-synchronous exchange, which waits for the
drive's next cycle, could not catch up: the deadlines take the drive's phase,
where whole periods skipped kept a lag of up to a period on every cycle). The
feedback is checked as in open loop
(:class:`~servobench.bench.run.feedback_check.FeedbackCheck`, with each
sample's host time): a repeated drive stamp is logged as read.

A guard stops the axis as soon as it leaves :data:`~servobench.bench.run.travel.MARGIN`
of the room around the held position (an unstable loop, or an excitation
the window cannot hold): the axis is stopped and disabled, the log is kept,
marked incomplete, and named in the one-line error.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from servobench.bench.log.io import LogWriter
from servobench.bench.run.feedback_check import FROZEN_CYCLES
from servobench.bench.run.hold import HoldLoop
from servobench.bench.run.ring_writer import RingLogWriter
from servobench.bench.run.runner import (
    DEFAULT_SETTLE_S,
    LOG_COLUMNS,
    REST_SAMPLES,
    ProgressCallback,
    _drain,
    _Plan,
    _reason,
    _sigterm_as_interrupt,
    _stats,
    _stop_quietly,
    _trailer,
    achieved_rate_hz,
    final_stop,
    kept_after_stop,
    note_partial_log,
)
from servobench.bench.run.timing_stats import CycleClock, CycleTiming, PeriodStats, TimingStats
from servobench.bench.run.travel import MARGIN, ClosedLoopPlan
from servobench.clock import sleep_until
from servobench.drivers.base import Drive, Feedback
from servobench.errors import LimitExceededError
from servobench.realtime import realtime_thread

#: Columns of a closed-loop log.
CLOSED_LOG_COLUMNS = (*LOG_COLUMNS, "u_exc", "x_ref")
#: A start closer than this share of the room to the held position needs no move.
CENTRE_TOLERANCE = 0.05
#: A move to the held position lasts this many periods of the hold's bandwidth.
MOVE_PERIODS = 1.5


@dataclass(frozen=True)
class ClosedRunResult:
    """What a closed-loop session produced.

    Attributes
    ----------
    log_path : Path
    samples : int
        Rows logged.
    timing : tuple of TimingStats
        Achieved timing per run.
    excursion : float
        Largest ``|x - x_ref|`` logged [position units].
    room : float
        Room on the nearer side of the held position [position units].
    """

    log_path: Path
    samples: int
    timing: tuple[TimingStats, ...]
    excursion: float
    room: float
    cycle_timing: CycleTiming | None = None  #: real pace: the host's cycle, all runs
    clock_source: str = ""  #: real pace: ``drive``, ``kernel`` or ``host``

    @property
    def share(self) -> float:
        """Share of the room used."""
        return self.excursion / self.room if self.room > 0 else math.inf

    @property
    def fs_achieved_hz(self) -> float:
        """Cycles per second the host achieved over every run, as in open loop (the log's
        ``fs_achieved``, :func:`~servobench.bench.run.runner.achieved_rate_hz`)."""
        return achieved_rate_hz(self.timing)


def stream_closed_runs(
    drive: Drive,
    runs: Sequence[tuple[int, np.ndarray]],
    fs_hz: float,
    log_path: str | Path,
    plan: ClosedLoopPlan,
    *,
    metadata: Mapping[str, object] | None = None,
    pace: str | None = None,
    settle_s: float = DEFAULT_SETTLE_S,
    progress: ProgressCallback | None = None,
    frozen_cycles: int = FROZEN_CYCLES,
) -> ClosedRunResult:
    """Apply each ``(run_number, u_exc)`` under the hold of ``plan`` and log it (see module docstring).

    Parameters are those of :func:`~servobench.bench.run.runner.stream_runs`,
    plus the plan. The drive is open; it is enabled here and left disabled.

    Raises
    ------
    LimitExceededError
        The axis left the margin of its travel (or the Drive layer's envelope).
    """
    checked = _Plan.make(drive, runs, fs_hz, pace, settle_s, progress, frozen_cycles, None)
    meta = {
        "fs": fs_hz, "drive": drive.url.raw, "pace": checked.pace,
        **drive.log_metadata(), **(metadata or {}), **plan.metadata(),
    }  # fmt: skip
    realtime = checked.pace == "real"
    rt = realtime_thread(helper_threads=drive.io_threads()) if realtime else contextlib.nullcontext()
    with rt as grant:
        columns = CLOSED_LOG_COLUMNS
        if grant is not None:
            meta = {"clock_source": drive.clock_source(), **grant.as_metadata(), **meta}
            columns = (*CLOSED_LOG_COLUMNS, "t_unc")
        writer = LogWriter(log_path, meta, columns, flush_every=1)
        sink = RingLogWriter(writer) if realtime else writer
        cycler = _Cycler(drive, plan, checked, sink)
        timing: list[TimingStats] = []
        try:
            with _sigterm_as_interrupt():
                cycler.session(runs, timing)
                stop_error = final_stop(drive)
        except BaseException as err:
            try:
                _stop_quietly(drive)
            finally:
                _drain(sink)
                writer.finish("incomplete", reason=_reason(err), samples=writer.rows,
                              **_trailer(drive, timing, cycler.clocks, checked.dt))  # fmt: skip
                note_partial_log(err, writer)
            raise
        _drain(sink)
        writer.finish("complete", samples=writer.rows, travel_excursion=cycler.excursion,
                      travel_share=cycler.excursion / plan.room,
                      **_trailer(drive, timing, cycler.clocks, checked.dt))  # fmt: skip
    if stop_error is not None:
        raise kept_after_stop(stop_error, log_path)
    cycle = CycleTiming.of(cycler.clocks, checked.dt) if realtime else None
    return ClosedRunResult(Path(log_path), writer.rows, tuple(timing), cycler.excursion, plan.room,
                           cycle, drive.clock_source() if realtime else "")  # fmt: skip


@dataclass
class _Row:
    """A logged row waiting for the command the drive reports it applied."""

    run: int
    t: float
    v: float
    x: float
    t_host: float
    u_exc: float
    x_ref: float
    sent: float
    t_unc: float = 0.0


class _Cycler:
    """Cycles the drive under the hold: paces, runs the host's loop, guards the margin, logs."""

    def __init__(
        self, drive: Drive, plan: ClosedLoopPlan, checked: _Plan, writer: LogWriter | RingLogWriter
    ) -> None:
        self.drive, self.plan, self.checked, self.writer = drive, plan, checked, writer
        self.realtime = checked.pace == "real"
        self.by_drive = drive.clock_source() == "drive"
        self.clocks: list[CycleClock] = []
        self.bracket = (0.0, 0.0)  # host clock before the request and after the answer [s]
        self.host = plan.host_controller()
        self.loop = HoldLoop(self.host)
        self.x_ref = plan.controller.x_ref
        self.limit = MARGIN * plan.room
        self.t0 = 0.0  # the deadlines' origin: set by anchor() before the first cycle
        self.paced = False  # the drive times the cycle (start_cycle_clock), no host schedule
        self.deadline = 0.0  # the last cycle's deadline on the host's clock [s]
        self.k = 0
        self.last: Feedback | None = None
        self.pending: _Row | None = None
        self.sent = 0.0  # the command sent in the last cycle (after the Drive layer's clamping)
        self.excursion = 0.0

    def session(self, runs: Sequence[tuple[int, np.ndarray]], timing: list[TimingStats]) -> None:
        drive, dt = self.drive, self.checked.dt
        drive.set_cycle(dt)
        drive.enable()
        self.paced = self.realtime and drive.start_cycle_clock(dt)
        try:
            self._session(runs, timing)
        finally:
            drive.stop_cycle_clock()

    def _session(self, runs: Sequence[tuple[int, np.ndarray]], timing: list[TimingStats]) -> None:
        """Move to the held position, enter the drive's hold, then each run after a rest."""
        drive = self.drive
        self.anchor()
        start = self.cycle(0.0)
        self.move(start.position)
        if self.plan.controller.where == "drive":
            drive.hold_position(self.x_ref)
            self.anchor()
        done = 0
        for number, u_exc in runs:
            self.rest()
            self.restart_loop()
            self.anchor()
            u_exc = np.asarray(u_exc, dtype=float)
            host, clock = PeriodStats(), PeriodStats()
            try:
                self.run(number, u_exc, done, host, clock)
            finally:
                timing.append(_stats(number, host, clock))
            done += len(u_exc)
        self.cycle(0.0)  # brings the read-back of the last row
        if drive.holding:
            drive.release_hold()

    # ----------------------------------------------------------------- phases
    def move(self, x_start: float) -> None:
        """Bring the axis from ``x_start`` to the held position with the host's loop."""
        target = self.plan.controller.x_ref
        if abs(target - x_start) <= CENTRE_TOLERANCE * self.plan.room:
            return
        m, dt = self.plan.model, self.checked.dt
        cycles = max(1, round(MOVE_PERIODS / self.host.gains.bandwidth_hz / dt))
        w, half = math.pi / (cycles * dt), 0.5 * (target - x_start)
        for k in range(cycles):
            phase = w * (k + 0.5) * dt  # the middle of the cycle the command acts over
            v_ref, a_ref = half * w * math.sin(phase), half * w * w * math.cos(phase)
            friction = m.coulomb_pos if v_ref > 0 else -m.coulomb_neg if v_ref < 0 else 0.0
            self.x_ref = self.loop.x_ref = x_start + half * (1.0 - math.cos(w * (k + 1) * dt))
            self._guard(self.cycle(m.M * a_ref + m.B * v_ref + friction))

    def rest(self) -> None:
        """Hold with no excitation until the axis rests (or ``settle_s`` passes)."""
        cycles = max(1, int(round(self.checked.settle_s / self.checked.dt)))
        peak, quiet = 0.0, 0
        for _ in range(cycles):
            fb = self.cycle(0.0)
            self._guard(fb)
            speed = abs(fb.velocity)
            peak = max(peak, speed)
            quiet = quiet + 1 if speed <= 1e-3 * peak or speed == 0.0 else 0
            if quiet >= REST_SAMPLES:
                return

    def restart_loop(self) -> None:
        """Start each run as the prediction does, the loop's integral at zero: while the axis
        rested against friction it wound up towards the breakaway level, which the excitation
        would add to. A drive's own loop forgets it on entering the hold again."""
        self.loop.reset()
        if self.drive.holding:
            self.drive.release_hold()
            self.drive.hold_position(self.x_ref)

    def run(self, number: int, u_exc: np.ndarray, done: int, host: PeriodStats, clock: PeriodStats) -> None:
        check = self.checked.feedback_check(self.drive, None)
        nominal = self.checked.pace == "fast" and not self.drive.drive_clock
        every = max(1, len(u_exc) // 200)
        cycle_clock = CycleClock(len(u_exc)) if self.realtime else None
        if cycle_clock is not None:
            self.clocks.append(cycle_clock)
        t0_host = time.monotonic()
        t0_drive = None
        acted = 0.0
        for k, uk in enumerate(u_exc.tolist()):
            fb = self.cycle(uk)
            # acted: the command of the cycle before; the host read the sample at bracket[1]
            check.check(fb.t_s, acted, fb.velocity, fb.position, self.bracket[1])
            acted = self.sent
            t_abs, t_unc = self.instant(fb)
            t0_drive = t_abs if t0_drive is None else t0_drive
            t_host = time.monotonic() - t0_host
            t = k * self.checked.dt if nominal else t_abs - t0_drive
            if cycle_clock is not None:
                start, end = self.bracket
                deadline = start if self.paced else self.deadline
                cycle_clock.mark(k, deadline, start, end, t_unc, fb.t_s)
            self.pending = _Row(number, t, fb.velocity, fb.position, t_host, uk, self.x_ref, acted, t_unc)
            self._guard(fb)
            host.add(t_host)
            clock.add(t)
            if self.checked.progress is not None and k % every == 0:
                self.checked.progress(done + k + 1, self.checked.total)
        if self.checked.progress is not None:
            self.checked.progress(done + len(u_exc), self.checked.total)

    def instant(self, fb: Feedback) -> tuple[float, float]:
        """The sample's best instant and its uncertainty [s] (see the runner's module docstring)."""
        if not self.realtime or self.by_drive:
            return fb.t_s, 0.0
        if fb.t_host_s == fb.t_host_s:
            return fb.t_host_s, fb.t_unc_s
        start, end = self.bracket
        return 0.5 * (start + end), 0.5 * (end - start)

    # ------------------------------------------------------------------ cycle
    def anchor(self) -> None:
        """The next cycle's deadline is now: after a step that is not a cycle (enabling,
        entering or restarting the drive's hold), the deadlines start again from here."""
        self.t0 = time.monotonic() - self.k * self.checked.dt

    def cycle(self, u_exc: float) -> Feedback:
        """One cycle: the command (the host's loop unless the drive holds), the exchange,
        and the row left pending by the cycle before."""
        if self.realtime and not self.paced:
            dt = self.checked.dt
            self.deadline = self.t0 + self.k * dt
            behind = time.monotonic() - self.deadline
            if behind > 0.5 * dt:  # over half a period late: start now, count on from here
                self.t0 += behind
            sleep_until(self.t0 + self.k * dt)
        self.k += 1
        if not self.drive.holding and self.last is not None:
            u = self.loop.command(u_exc, self.last.position, self.last.velocity)
        else:
            u = u_exc
        try:
            start = time.monotonic()
            fb, self.sent = self.drive.exchange(u)
            self.bracket = (start, time.monotonic())
        except BaseException:
            self._write_pending(math.nan)  # no sample taken is lost
            raise
        self._write_pending(fb.applied)
        self.last = fb
        return fb

    def _write_pending(self, applied: float) -> None:
        row, self.pending = self.pending, None
        if row is None:
            return
        u = applied if math.isfinite(applied) else row.sent
        if self.realtime:
            self.writer.append(row.run, row.t, u, row.v, row.x, row.t_host, row.u_exc, row.x_ref, row.t_unc)
        else:
            self.writer.append(row.run, row.t, u, row.v, row.x, row.t_host, row.u_exc, row.x_ref)
        self.excursion = max(self.excursion, abs(row.x - row.x_ref))

    def _guard(self, fb: Feedback) -> None:
        if abs(fb.position - self.x_ref) <= self.limit:
            return
        self._write_pending(math.nan)
        _stop_quietly(self.drive)
        raise LimitExceededError(
            f"axis stopped: the hold loop could not keep it within {MARGIN:.0%} of its room "
            f"(x = {fb.position:.4g}, held at {self.x_ref:.4g}, room {self.plan.room:.4g}); "
            f"partial log kept in {self.writer.path}. Lower the amplitude, raise the lowest "
            "excited line, or widen xmin/xmax"
        )
