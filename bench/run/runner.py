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
drive clock must advance, and the feedback must not be frozen -- position
and velocity bit-identical for ``frozen_cycles`` cycles while the drive
reports motion that should have moved the position by now, or while the
command stays at or above ``breakaway`` when the caller knows it (see
:class:`FeedbackCheck`). Any of them ends the run with
:class:`~servobench.errors.DriveError`.

Memory is O(1) in the run length: timing statistics are streamed
(Welford), samples go straight to the file.
"""

from __future__ import annotations

import contextlib
import math
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from servobench.bench.log.identity import run_identity
from servobench.bench.log.io import LogWriter
from servobench.bench.run.feedback_check import FROZEN_CYCLES, FeedbackCheck
from servobench.bench.run.timing_stats import PeriodStats, TimingStats
from servobench.clock import sleep_until
from servobench.drivers.base import Drive
from servobench.errors import DriveError, LimitExceededError, UsageError, add_note

#: Columns of a runner log.
LOG_COLUMNS = ("run", "t", "u", "v", "x", "t_host")
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
    writer = LogWriter(log_path, meta, LOG_COLUMNS, flush_every=1)
    timing: list[TimingStats] = []
    try:
        with _sigterm_as_interrupt():
            _stream_all(drive, runs, plan, writer, timing)
    except BaseException as err:
        try:
            _stop_quietly(drive)
        finally:
            writer.finish(
                "incomplete", reason=_reason(err), samples=writer.rows, **_trailer(drive, timing)
            )
            note_partial_log(err, writer)
        raise
    writer.finish("complete", samples=writer.rows, **_trailer(drive, timing))
    return RunResult(Path(log_path), writer.rows, tuple(timing), True)


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
        return cls(1.0 / fs_hz, pace, settle_s, progress, frozen_cycles, breakaway, total)


def _stream_all(
    drive: Drive,
    runs: Sequence[tuple[int, np.ndarray]],
    plan: _Plan,
    writer: LogWriter,
    timing: list[TimingStats],
) -> None:
    """Enable, stream every run (resting between them), then stop and disable."""
    drive.set_cycle(plan.dt)
    drive.enable()
    done = 0
    for index, (number, u) in enumerate(runs):
        u = np.asarray(u, dtype=float)
        if index:
            _settle(drive, plan.dt, plan.settle_s, plan.pace)
        check = FeedbackCheck(plan.frozen_cycles, plan.breakaway, drive.drive_clock, plan.dt)
        run = _Run(number, writer, check, plan.progress, done, plan.total)
        try:
            if plan.pace == "fast" and drive.supports_block:
                _stream_blocks(drive, u, run)
            else:
                _stream_samples(drive, u, plan.dt, plan.pace, run)
        finally:
            timing.append(_stats(number, run.host, run.clock))
        done += len(u)
    drive.stop()
    drive.disable()


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


def _trailer(drive: Drive, timing: list[TimingStats]) -> dict[str, object]:
    extra: dict[str, object] = {k: v for s in timing for k, v in s.as_metadata().items()}
    achieved = achieved_rate_hz(timing)
    if math.isfinite(achieved):
        extra["fs_achieved"] = round(achieved, 4)
    for name, count in drive.link_recoveries().items():
        if count:
            extra[f"link_{name}"] = count
    return extra


@dataclass
class _Run:
    """One run being streamed: where its samples go and what watches them."""

    number: int
    writer: LogWriter
    check: FeedbackCheck
    progress: ProgressCallback | None
    done: int  # samples of earlier runs
    total: int  # samples of all runs
    host: PeriodStats = field(default_factory=PeriodStats)
    clock: PeriodStats = field(default_factory=PeriodStats)

    def report(self, done_here: int) -> None:
        if self.progress is not None:
            self.progress(self.done + done_here, self.total)


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
        run.check.check(fb.t_s, acted, fb.velocity, fb.position)
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
        good = run.check.first_failure(block.t_s, prev_u, block.velocity, block.position)
        if (
            good < len(td)
        ):  # an earlier failed feedback check wins over a later limit breach  # log the good head, then fail with the check's message
            try:
                run.check.check(
                    float(block.t_s[good]), float(prev_u[good]),
                    float(block.velocity[good]), float(block.position[good]),
                )  # fmt: skip
                failure = DriveError(f"feedback check failed at sample {start + good}")
            except DriveError as err:
                failure = err
        th = np.full(good, now)
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
