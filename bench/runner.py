"""Stream excitation runs to any :class:`~drivers.base.Drive` and log them as they arrive.

The runner is transport-agnostic: it sets the drive's cycle, enables it,
streams each run sample by sample (or in blocks for drives that simulate
faster than real time), lets the axis come to rest between runs, and writes
every sample to the log the moment it is taken. On Ctrl-C or any error it
quick-stops and disables the axis, marks the log incomplete with the reason,
and re-raises.

Pacing: with ``pace="real"`` the host holds a fixed-rate schedule
(``t0 + k/fs`` deadlines on ``time.monotonic``) as a real bench must; with
``pace="fast"`` it streams as fast as the link answers (for lock-step
simulated drives and batch work).
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.logio import LogWriter
from drivers.base import Drive
from drivers.errors import DriveError, UsageError

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


@dataclass(frozen=True)
class RunResult:
    """What a streaming session produced."""

    log_path: Path
    samples: int
    timing: tuple[TimingStats, ...]
    complete: bool


def _stats(run: int, t_host: np.ndarray, t_drive: np.ndarray) -> TimingStats:
    def moments(t: np.ndarray) -> tuple[float, float, float]:
        if t.size < 2:
            return math.nan, math.nan, math.nan
        d = np.diff(t)
        return float(d.mean()), float(d.std()), float(d.max())

    hm, hs, hx = moments(t_host)
    dm, ds, _ = moments(t_drive)
    return TimingStats(run, int(t_host.size), hm, hs, hx, dm, ds)


def _default_pace(drive: Drive) -> str:
    """``"fast"`` for drives that say they are not real-time (``realtime = False``), else ``"real"``."""
    return "fast" if getattr(drive, "realtime", True) is False else "real"


def _sleep_until(deadline: float) -> None:
    """Sleep coarsely, then spin for the last half millisecond (jitter << 1 ms)."""
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            return
        if left > 6e-4:
            time.sleep(left - 5e-4)


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
        Extra ``# key = value`` header lines (``fs`` is always written).
    pace : {"real", "fast"}, optional
        Default: the drive's ``pace`` URL key, else ``"fast"`` for a drive whose
        ``realtime`` attribute is False (``sim://``), else ``"real"``.
    settle_s : float
        Longest rest with zero command between runs [s].
    progress : callable(done, total), optional
        Called after each block of samples.

    Returns
    -------
    RunResult
    """
    if not (math.isfinite(fs_hz) and fs_hz > 0):
        raise UsageError(f"sample rate must be > 0 Hz, got {fs_hz}")
    pace = pace or drive.url.get_str("pace", "") or _default_pace(drive)
    if pace not in ("real", "fast"):
        raise UsageError(f"pace must be 'real' or 'fast', got {pace!r}")
    dt = 1.0 / fs_hz
    total = int(sum(len(u) for _, u in runs))
    meta = {"fs": fs_hz, "drive": drive.url.raw, "pace": pace, **(metadata or {})}
    writer = LogWriter(log_path, meta, LOG_COLUMNS, flush_every=1 if pace == "real" else 256)
    timing: list[TimingStats] = []
    done = 0
    try:
        drive.set_cycle(dt)
        drive.enable()
        for index, (number, u) in enumerate(runs):
            u = np.asarray(u, dtype=float)
            if index:
                _settle(drive, dt, settle_s, pace)
            use_block = pace == "fast" and getattr(drive, "supports_block", False)
            if use_block:
                th, td = _stream_blocks(drive, number, u, writer, progress, done, total)
            else:
                th, td = _stream_samples(drive, number, u, dt, pace, writer, progress, done, total)
            done += len(u)
            timing.append(_stats(number, th, td))
        drive.stop()
        drive.disable()
    except BaseException as err:
        with contextlib.suppress(DriveError, OSError):
            drive.stop()
        with contextlib.suppress(DriveError, OSError):
            drive.disable()
        reason = "interrupted (Ctrl-C)" if isinstance(err, KeyboardInterrupt) else str(err)
        extra = {k: v for s in timing for k, v in s.as_metadata().items()}
        writer.finish("incomplete", reason=reason or type(err).__name__, samples=writer.rows, **extra)
        raise
    extra = {k: v for s in timing for k, v in s.as_metadata().items()}
    writer.finish("complete", samples=writer.rows, **extra)
    return RunResult(Path(log_path), writer.rows, tuple(timing), True)


def _stream_samples(
    drive: Drive,
    number: int,
    u: np.ndarray,
    dt: float,
    pace: str,
    writer: LogWriter,
    progress: ProgressCallback | None,
    done: int,
    total: int,
) -> tuple[np.ndarray, np.ndarray]:
    n = len(u)
    t_host = np.empty(n)
    t_drive = np.empty(n)
    t0_host = time.monotonic()
    t0_drive = None
    # Without a drive clock, a lock-step drive streamed fast is clocked once per
    # exchange: its sample times are the nominal grid, not host reception times.
    nominal = dt if (pace == "fast" and not drive.drive_clock) else None
    every = max(1, n // 200)
    for k in range(n):
        if pace == "real":
            _sleep_until(t0_host + k * dt)
        fb, applied = drive.exchange(u[k])
        now = time.monotonic()
        if t0_drive is None:
            t0_drive = fb.t_s
        t_host[k] = now - t0_host
        t_drive[k] = fb.t_s - t0_drive if nominal is None else k * nominal
        writer.append(number, t_drive[k], applied, fb.velocity, fb.position, t_host[k])
        if progress is not None and k % every == 0:
            progress(done + k + 1, total)
    if progress is not None:
        progress(done + n, total)
    return t_host, t_drive


def _stream_blocks(
    drive: Drive,
    number: int,
    u: np.ndarray,
    writer: LogWriter,
    progress: ProgressCallback | None,
    done: int,
    total: int,
) -> tuple[np.ndarray, np.ndarray]:
    hosts: list[np.ndarray] = []
    drives: list[np.ndarray] = []
    t0_host = time.monotonic()
    t0_drive = None
    for start in range(0, len(u), BLOCK_CYCLES):
        block = drive.exchange_block(u[start : start + BLOCK_CYCLES])
        now = time.monotonic() - t0_host
        if t0_drive is None:
            t0_drive = float(block.t_s[0])
        td = block.t_s - t0_drive
        th = np.full(td.shape, now)
        writer.append_block(np.full(td.shape, number), td, block.applied, block.velocity, block.position, th)
        hosts.append(th)
        drives.append(td)
        if progress is not None:
            progress(done + start + len(td), total)
    return np.concatenate(hosts), np.concatenate(drives)


def _settle(drive: Drive, dt: float, settle_s: float, pace: str) -> None:
    """Zero command until the axis rests (``REST_SAMPLES`` samples at rest) or ``settle_s`` passes."""
    cycles = max(1, int(round(settle_s / dt)))
    t0 = time.monotonic()
    peak = 0.0
    quiet = 0
    for k in range(cycles):
        if pace == "real":
            _sleep_until(t0 + k * dt)
        fb, _ = drive.exchange(0.0)
        speed = abs(fb.velocity)
        peak = max(peak, speed)
        quiet = quiet + 1 if speed <= 1e-3 * peak or speed == 0.0 else 0
        if quiet >= REST_SAMPLES:
            return
