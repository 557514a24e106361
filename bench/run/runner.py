"""Stream excitation runs to any :class:`~servobench.drivers.base.Drive` and log them as they arrive.

The runner is transport-agnostic: it sets the drive's cycle, enables it,
streams each run sample by sample (or in blocks for drives that simulate
faster than real time), lets the axis come to rest between runs, and writes
every sample to the log the moment it is taken (flushed to the OS per
sample, per block in block mode). On Ctrl-C, SIGTERM or any error it
quick-stops and disables the axis, marks the log incomplete with the
one-line reason, and re-raises; a host killed outright leaves a log whose
header says ``status = running``, which readers take as incomplete.

Pacing: with ``pace="real"`` the host holds a fixed-rate schedule
(``t0 + k/fs`` deadlines on ``time.monotonic``) as a real bench must; with
``pace="fast"`` it streams as fast as the link answers (for lock-step
simulated drives and batch work).

Checks on every sample, before it is logged: feedback must be finite, a
drive clock must not go back nor stand still for longer than the watchdog
the drive URL sets (else :data:`~servobench.bench.run.feedback_check.STAMP_STILL_S`)
of host time, and the feedback must not be frozen -- position
and velocity bit-identical for ``frozen_cycles`` cycles while the drive
reports motion that should have moved the position by now, or while the
command stays at or above ``breakaway`` when the caller knows it (see
:class:`FeedbackCheck`). Any of them ends the run with
:class:`~servobench.errors.DriveError`. A drive's time stamp equal to the
one before is a repeated sample (two reads within one tick of the drive):
logged as read, with its equal ``t``.

Real time (``pace="real"``): the calling thread becomes the cyclic thread
and takes the best footing the OS grants (:func:`servobench.realtime.realtime_thread`:
``SCHED_FIFO``, one CPU, locked memory, the garbage collector frozen, a short
GIL switch interval; the drive's receive threads just below it), logged as
``rt_*`` lines. It does nothing but the exchange and its own measurement:
rows go through a preallocated ring to a writer thread
(:mod:`servobench.bench.run.ring_writer`), which writes them as they arrive.
Each sample gets its best instant and its uncertainty, ``t`` and the extra
column ``t_unc`` [s] (the log's ``# clock_source`` says which):
``drive`` -- the drive's time stamp, ``t_unc`` 0; ``kernel`` or ``host`` --
the interval the transport knows holds the sample (``Feedback.t_host_s``,
``Feedback.t_unc_s``), else
the host clock just before the request and just after the answer, ``t`` its
midpoint and ``t_unc`` its half-width. Where the transport times the cycle
itself (:meth:`~servobench.drivers.base.Drive.start_cycle_clock`, the SYNC of
the kernel's broadcast manager on SocketCAN) the host holds no schedule.
The trailer carries the cycle's timing (:class:`~servobench.bench.run.timing_stats.CycleTiming`:
``host_jitter_p50_s``, ``host_jitter_p99_s``, ``host_jitter_max_s``,
``missed_cycles``, ``late_cycles``, ``t_unc_p50_s`` ... overall and per run)
and, in a log whose ``clock_source`` is ``drive``, the drive's tick read from
its stamps (:class:`~servobench.bench.run.timing_stats.DriveTicks`:
``repeated_samples``, ``skipped_ticks``, ``drive_tick_s`` when the stamps show
a tick, and ``run<n>_repeated_samples``, ``run<n>_skipped_ticks``). A drive
that says where each command took force (an EtherCAT DC-synchronous slave)
adds the column ``t_act`` [s, the clock of ``t``] and the trailer's
``late_samples``: rows whose command acted before their sample
(:mod:`servobench.bench.run.cyclic`).

Lock-step drives streamed fast (``pace="fast"``) keep the exact nominal or
drive clock, block exchange and no ``t_unc`` column, as fast as before.

Memory is O(1) in the run length in fast pace: timing statistics are
streamed (Welford), samples go straight to the file; in real pace the
per-cycle instants are kept in arrays allocated before each run.
"""

from __future__ import annotations

import contextlib
import math
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from servobench.bench.log.identity import run_identity
from servobench.bench.log.io import LogWriter
from servobench.bench.run.cyclic import Run as _Run
from servobench.bench.run.cyclic import stream_realtime as _stream_realtime
from servobench.bench.run.feedback_check import FROZEN_CYCLES, STAMP_STILL_S, FeedbackCheck
from servobench.bench.run.ring_writer import RingLogWriter
from servobench.bench.run.timing_stats import (
    CycleClock,
    CycleTiming,
    DriveTicks,
    PeriodStats,
    TimingStats,
)
from servobench.clock import sleep_until
from servobench.drivers.base import Drive
from servobench.errors import DriveError, LimitExceededError, UsageError, add_note
from servobench.realtime import RealtimeGrant, realtime_thread

#: Columns of a runner log.
LOG_COLUMNS = ("run", "t", "u", "v", "x", "t_host")
#: Columns of a real-time runner log: the sample's timing uncertainty [s] added at the end.
REALTIME_COLUMNS = (*LOG_COLUMNS, "t_unc")
#: Cycles streamed per block to drives that support block exchange.
BLOCK_CYCLES = 2000
#: Longest rest between runs [s].
DEFAULT_SETTLE_S = 1.0
#: Consecutive samples at rest that end the settle phase early.
REST_SAMPLES = 20

ProgressCallback = Callable[[int, int], None]


@dataclass(frozen=True)
class RunResult:
    """What a streaming session produced."""

    log_path: Path
    samples: int
    timing: tuple[TimingStats, ...]
    complete: bool
    cycle_timing: CycleTiming | None = None  #: real pace: the host's cycle, all runs
    clock_source: str = ""  #: real pace: ``drive``, ``kernel`` or ``host``

    @property
    def fs_achieved_hz(self) -> float:
        """Cycles per second the host achieved, over every run (:func:`achieved_rate_hz`)."""
        return achieved_rate_hz(self.timing)


def achieved_rate_hz(timing: Sequence[TimingStats]) -> float:
    """Cycles per second the host achieved [Hz]: all periods of all runs over their total time."""
    periods = sum(max(0, t.samples - 1) for t in timing)
    elapsed_s = sum(max(0, t.samples - 1) * t.host_period_mean_s for t in timing if t.samples > 1)
    return periods / elapsed_s if elapsed_s > 0 else math.nan


def _stats(run: int, host: PeriodStats, drive: PeriodStats) -> TimingStats:
    return TimingStats(run, host.samples, host.mean, host.std, host.max, drive.mean, drive.std)


class TerminatedError(KeyboardInterrupt):
    """SIGTERM arrived while streaming: handled like Ctrl-C (axis stopped, log kept)."""


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """In the main thread, turn SIGTERM into :class:`TerminatedError` for the duration."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: object) -> None:
        raise TerminatedError("terminated (SIGTERM)")

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not allowed here (e.g. embedded interpreters)
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def default_pace(drive: Drive) -> str:
    """``"fast"`` for a lock-step drive (``Drive.realtime`` False), else ``"real"``."""
    return "real" if drive.realtime else "fast"


def stream_runs(
    drive: Drive,
    runs: Sequence[tuple[int, np.ndarray]],
    fs_hz: float,
    log_path: str | Path,
    *,
    metadata: Mapping[str, object] | None = None,
    pace: str | None = None,
    settle_s: float = DEFAULT_SETTLE_S,
    progress: ProgressCallback | None = None,
    frozen_cycles: int = FROZEN_CYCLES,
    breakaway: float | None = None,
) -> RunResult:
    """Apply each ``(run_number, u)`` to an open drive and log ``run,t,u,v,x,t_host``.

    ``t`` is the drive's sample clock when the drive has one; otherwise the
    host's reception time, except with ``pace="fast"`` (a lock-step drive
    clocked once per exchange), where it is the nominal grid ``k/fs``.

    Parameters
    ----------
    drive : Drive
        An open drive; it is enabled here and left disabled.
    runs : sequence of (int, ndarray)
        Run numbers and commands [command units], one sample per cycle.
    fs_hz : float
        Cycle rate [Hz].
    log_path : path
        CSV log, written as samples arrive.
    metadata : mapping
        Extra ``# key = value`` header lines. ``fs`` is always written, and so are
        ``axis`` and ``time`` (:func:`~servobench.bench.log.identity.run_identity`),
        which ``metadata`` may override.
    pace : {"real", "fast"}, optional
        Default: the drive's ``pace`` URL key, else ``"fast"`` for a drive whose
        ``realtime`` is False (``sim://``), else ``"real"``.
    settle_s : float
        Longest rest with zero command between runs [s].
    progress : callable(done, total), optional
        Called after each block of samples.
    frozen_cycles : int
        Bit-identical feedback samples that mean "feedback frozen" (0: never).
    breakaway : float, optional
        Command magnitude [command units] that surely moves the axis, when known:
        frozen feedback is then caught at rest too.

    Returns
    -------
    RunResult
    """
    plan = _Plan.make(drive, runs, fs_hz, pace, settle_s, progress, frozen_cycles, breakaway)
    meta = {
        "fs": fs_hz, "drive": drive.url.raw, "pace": plan.pace, **run_identity(drive),
        **drive.log_metadata(), **(metadata or {}),
    }  # fmt: skip
    realtime = plan.pace == "real"
    rt = realtime_thread(helper_threads=drive.io_threads()) if realtime else contextlib.nullcontext()
    with rt as grant:
        columns = LOG_COLUMNS
        if grant is not None:
            meta, columns = realtime_header(drive, grant, meta), realtime_columns(drive)
        writer = LogWriter(log_path, meta, columns, flush_every=1)
        sink = RingLogWriter(writer) if realtime else writer
        timing: list[TimingStats] = []
        clocks: list[CycleClock] = []
        try:
            with _sigterm_as_interrupt():
                _stream_all(drive, runs, plan, sink, timing, clocks)
                stop_error = final_stop(drive)
        except BaseException as err:
            try:
                _stop_quietly(drive)
            finally:
                _drain(sink)
                writer.finish(
                    "incomplete", reason=_reason(err), samples=writer.rows,
                    **_trailer(drive, timing, clocks, plan.dt),
                )  # fmt: skip
                note_partial_log(err, writer)
            raise
        _drain(sink)
        writer.finish("complete", samples=writer.rows, **_trailer(drive, timing, clocks, plan.dt))
    if stop_error is not None:
        raise kept_after_stop(stop_error, log_path)
    cycle = CycleTiming.of(clocks, plan.dt) if realtime else None
    source = drive.clock_source() if realtime else ""
    return RunResult(Path(log_path), writer.rows, tuple(timing), True, cycle, source)


def realtime_columns(drive: Drive) -> tuple[str, ...]:
    """A real-time log's columns: :data:`REALTIME_COLUMNS`, and ``t_act`` where the drive says
    where each command took force (:meth:`~servobench.drivers.base.Drive.reports_action_instant`)."""
    return (*REALTIME_COLUMNS, "t_act") if drive.reports_action_instant() else REALTIME_COLUMNS


def realtime_header(drive: Drive, grant: RealtimeGrant, meta: Mapping[str, object]) -> dict[str, object]:
    """A real-time log's header: where its instants come from (``clock_source``), the
    command lead where the drive has one, what the OS granted (``rt_*``), then ``meta``."""
    lead = {"command_lead_s": drive.command_lead_s()} if drive.command_lead_s() > 0 else {}
    return {"clock_source": drive.clock_source(), **lead, **grant.as_metadata(), **meta}


def _drain(sink: LogWriter | RingLogWriter) -> None:
    """Every row the ring still holds written (nothing to do for a plain writer)."""
    if isinstance(sink, RingLogWriter):
        sink.close()


def note_partial_log(err: BaseException, writer: LogWriter) -> None:
    """Name the partial log ``writer`` kept in ``err``'s notes (the CLI ends its one line with
    them), unless the message names it already."""
    if str(writer.path) not in str(err):
        add_note(err, f"partial log kept: {writer.path} ({writer.rows} samples, marked incomplete)")


@dataclass(frozen=True)
class _Plan:
    """The checked options of one streaming session."""

    dt: float  # cycle period [s]
    pace: str  # "real" or "fast"
    settle_s: float
    progress: ProgressCallback | None
    frozen_cycles: int
    breakaway: float | None
    total: int  # samples of all runs
    still_s: float = STAMP_STILL_S  # host time a drive clock's stamp may stand still [s]

    @classmethod
    def make(cls, drive, runs, fs_hz, pace, settle_s, progress, frozen_cycles, breakaway) -> _Plan:
        if not (math.isfinite(fs_hz) and fs_hz > 0):
            raise UsageError(f"sample rate must be > 0 Hz, got {fs_hz}")
        if frozen_cycles < 0 or (breakaway is not None and not breakaway > 0):
            raise UsageError("frozen_cycles must be >= 0 and breakaway > 0")
        pace = pace or drive.url.get_str("pace", "") or default_pace(drive)
        if pace not in ("real", "fast"):
            raise UsageError(f"pace must be 'real' or 'fast', got {pace!r}")
        total = int(sum(len(u) for _, u in runs))
        still = stamp_still_s(drive)
        return cls(1.0 / fs_hz, pace, settle_s, progress, frozen_cycles, breakaway, total, still)

    def feedback_check(self, drive: Drive, breakaway: float | None) -> FeedbackCheck:
        """A run's :class:`FeedbackCheck` on this session's terms."""
        return FeedbackCheck(self.frozen_cycles, breakaway, drive.drive_clock, self.dt, self.still_s)


def stamp_still_s(drive: Drive) -> float:
    """Host time the drive's time stamp may stand still while enabled [s]: the watchdog its URL
    sets, else :data:`~servobench.bench.run.feedback_check.STAMP_STILL_S` (the default watchdog
    of the Drive layer, half a second, is not taken: it would leave half a second of stale
    feedback unseen)."""
    return getattr(drive, "watchdog_s", STAMP_STILL_S) if "watchdog" in drive.url.query else STAMP_STILL_S


def _stream_all(
    drive: Drive,
    runs: Sequence[tuple[int, np.ndarray]],
    plan: _Plan,
    writer: LogWriter | RingLogWriter,
    timing: list[TimingStats],
    clocks: list[CycleClock],
) -> None:
    """Enable, stream every run (resting between them), then stop and disable."""
    drive.set_cycle(plan.dt)
    drive.enable()
    source = drive.clock_source()
    paced_by_drive = plan.pace == "real" and drive.start_cycle_clock(plan.dt)
    try:
        done = 0
        for index, (number, u) in enumerate(runs):
            u = np.asarray(u, dtype=float)
            if index:
                _settle(drive, plan.dt, plan.settle_s, "fast" if paced_by_drive else plan.pace)
            check = plan.feedback_check(drive, plan.breakaway)
            run = _Run(number, writer, check, plan.progress, done, plan.total)
            try:
                if plan.pace == "fast" and drive.supports_block:
                    _stream_blocks(drive, u, run)
                elif plan.pace == "fast":
                    _stream_samples(drive, u, plan.dt, plan.pace, run)
                else:
                    clock = CycleClock(len(u))
                    clocks.append(clock)
                    _stream_realtime(drive, u, plan.dt, paced_by_drive, run, clock, source)
            finally:
                timing.append(_stats(number, run.host, run.clock))
            done += len(u)
    finally:
        drive.stop_cycle_clock()


def final_stop(drive: Drive) -> DriveError | None:
    """Stop and disable the axis after the last sample; a failure is returned, not raised.

    The Drive layer already brings a drive that ignores its quick stop to rest by
    disabling it, and says so in :attr:`~servobench.drivers.base.Drive.remarks`; what
    reaches here is an axis that could not be stopped at all. Every sample was
    received by then: the caller keeps the complete log (the remark in its
    trailer) and raises the error afterwards (:func:`kept_after_stop`).
    """
    try:
        drive.stop()
        drive.disable()
    except DriveError as err:
        drive.remarks.append(f"the axis did not stop after the last sample: {err}")
        return err
    return None


def kept_after_stop(err: DriveError, log_path: str | Path) -> DriveError:
    """The error of a failed final stop, naming the complete log that was kept."""
    return type(err)(f"{err}; every sample was received and the complete log is kept in {log_path} "
                     "(servobench identify can read it)")  # fmt: skip


def _reason(err: BaseException) -> str:
    """The one-line reason an interrupted session gives in its log trailer."""
    if isinstance(err, KeyboardInterrupt) and not isinstance(err, TerminatedError):
        return "interrupted (Ctrl-C)"
    return str(err) or type(err).__name__


def _stop_quietly(drive: Drive) -> None:
    """Quick stop and disable after a failure; their own failures must not hide it."""
    with contextlib.suppress(Exception):
        drive.stop()
    with contextlib.suppress(Exception):
        drive.disable()


def _trailer(
    drive: Drive, timing: list[TimingStats], clocks: list[CycleClock], dt: float
) -> dict[str, object]:
    extra: dict[str, object] = {k: v for s in timing for k, v in s.as_metadata().items()}
    if clocks:
        for s, clock in zip(timing, clocks, strict=False):
            extra.update(CycleTiming.of([clock], dt).as_metadata(f"run{s.run}_"))
        extra.update(CycleTiming.of(clocks, dt).as_metadata())
        for name, count in drive.cycle_counts().items():
            extra[name] = count
        if any(c.action_instants for c in clocks):
            extra["late_samples"] = sum(c.late_samples for c in clocks)
        if any(c.read_back for c in clocks):
            extra["u_read_back"] = "torque actual 0x6077 with the next sample"
            extra["late_commands"] = sum(c.late_commands for c in clocks)
        if drive.clock_source() == "drive":
            stamps = [(s.run, c.stamp[: c.count]) for s, c in zip(timing, clocks, strict=False)]
            ticks = DriveTicks.of(stamps)
            if ticks is not None:
                extra.update(ticks.as_metadata())
    achieved = achieved_rate_hz(timing)
    if math.isfinite(achieved):
        extra["fs_achieved"] = round(achieved, 4)
    for name, count in drive.link_recoveries().items():
        if count:
            extra[f"link_{name}"] = count
    if drive.remarks:  # how the axis was stopped, objects it refused
        extra["remarks"] = "; ".join(drive.remarks)
    return extra



def _stream_samples(drive: Drive, u: np.ndarray, dt: float, pace: str, run: _Run) -> None:
    n = len(u)
    t0_host = time.monotonic()
    t0_drive = None
    # Without a drive clock, a lock-step drive streamed fast is clocked once per
    # exchange: its sample times are the nominal grid, not host reception times.
    nominal = dt if (pace == "fast" and not drive.drive_clock) else None
    every = max(1, n // 200)
    acted = 0.0  # the command that acted over the cycle before this sample
    for k in range(n):
        if pace == "real":
            sleep_until(t0_host + k * dt)
        fb, applied = drive.exchange(u[k])
        now = time.monotonic()
        run.check.check(fb.t_s, acted, fb.velocity, fb.position, now)
        acted = applied
        if t0_drive is None:
            t0_drive = fb.t_s
        t_host = now - t0_host
        t_drive = fb.t_s - t0_drive if nominal is None else k * nominal
        run.writer.append(run.number, t_drive, applied, fb.velocity, fb.position, t_host)
        run.host.add(t_host)
        run.clock.add(t_drive)
        if k % every == 0:
            run.report(k + 1)
    run.report(n)



def _stream_blocks(drive: Drive, u: np.ndarray, run: _Run) -> None:
    t0_host = time.monotonic()
    t0_drive = None
    last_u = 0.0
    for start in range(0, len(u), BLOCK_CYCLES):
        failure: DriveError | None = None
        try:
            block = drive.exchange_block(u[start : start + BLOCK_CYCLES])
        except LimitExceededError as err:
            if err.partial is None:
                raise
            block, failure = err.partial, err  # log the cycles taken, then fail
        now = time.monotonic() - t0_host
        if t0_drive is None:
            t0_drive = float(block.t_s[0])
        td = block.t_s - t0_drive
        prev_u = np.concatenate(([last_u], block.applied[:-1]))
        t_host = np.full(len(td), now)
        good = run.check.first_failure(block.t_s, prev_u, block.velocity, block.position, t_host)
        if (
            good < len(td)
        ):  # an earlier failed feedback check wins over a later limit breach  # log the good head, then fail with the check's message
            try:
                run.check.check(
                    float(block.t_s[good]), float(prev_u[good]),
                    float(block.velocity[good]), float(block.position[good]), now,
                )  # fmt: skip
                failure = DriveError(f"feedback check failed at sample {start + good}")
            except DriveError as err:
                failure = err
        th = t_host[:good]
        run.writer.append_block(
            np.full(good, run.number), td[:good], block.applied[:good], block.velocity[:good],
            block.position[:good], th,
        )  # fmt: skip
        run.host.add_block(th)
        run.clock.add_block(td[:good])
        if failure is not None:
            raise failure
        last_u = float(block.applied[-1]) if len(block.applied) else last_u
        run.report(start + len(td))


def _settle(drive: Drive, dt: float, settle_s: float, pace: str) -> None:
    """Zero command until the axis rests (``REST_SAMPLES`` samples at rest) or ``settle_s`` passes."""
    cycles = max(1, int(round(settle_s / dt)))
    t0 = time.monotonic()
    peak = 0.0
    quiet = 0
    for k in range(cycles):
        if pace == "real":
            sleep_until(t0 + k * dt)
        fb, _ = drive.exchange(0.0)
        speed = abs(fb.velocity)
        peak = max(peak, speed)
        quiet = quiet + 1 if speed <= 1e-3 * peak or speed == 0.0 else 0
        if quiet >= REST_SAMPLES:
            return
