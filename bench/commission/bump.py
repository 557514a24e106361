"""Step 3: the bump test -- short pulses each way at a small fraction of the limit.

Before the long excitation the axis gets a few short command pulses, the
smallest first (``[bump] fractions`` of max_u), in the positive and then the
negative direction, each followed by a zero-command coast until it rests.
For each direction the test answers:

* does it move (peak ``|v|`` or ``|dx|`` above the noise seen at rest)?
* in the right direction (positive command -> positive velocity)?
* is the feedback sane: finite, the drive clock advancing, and the position
  change consistent with the integrated velocity (judged where the motion is
  large against the position noise and against what the velocity's own
  resolution, e.g. whole rpm, can put into its integral)?

Any "no" refuses commissioning with what to change. Every sample goes to
``bump.csv`` as it is taken (run = pulse number), kept even on Ctrl-C.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from servobench.bench.commission.config import BumpSettings
from servobench.bench.commission.errors import CommissionRefused
from servobench.bench.commission.limits import ConfirmedLimits
from servobench.bench.identify.resolution import signal_step
from servobench.bench.run.reactive import ReactiveCycle
from servobench.drivers.base import Drive
from servobench.errors import DriveError

#: Cycles at zero command before the first pulse (noise estimate).
REST_CYCLES = 50
#: Consecutive quiet samples that end a coast.
QUIET_SAMPLES = 20
#: Motion threshold over the standard deviation seen at rest.
NOISE_FACTOR = 6.0
#: Motion threshold floor [fraction of max_v].
MIN_SPEED_FRACTION = 1e-3
#: A pulse also ends when the axis has covered this fraction of a finite travel span.
MAX_TRAVEL_FRACTION = 0.1
#: The position check needs a displacement this many times the position noise/quantum.
POSITION_JUDGE_FACTOR = 20.0

ProgressCallback = Callable[[int, int], None]


@dataclass(frozen=True)
class BumpPulse:
    """One pulse and what it did.

    Attributes
    ----------
    number : int
        Pulse number (the ``run`` column of ``bump.csv``).
    amplitude : float
        Command applied, signed [command units].
    peak_velocity : float
        Largest velocity change from the pulse start, signed [velocity units/s].
    displacement : float
        Position change over pulse and coast [position units].
    integrated : float
        Trapezoidal integral of the velocity over the same samples [position units].
    moved : bool
        Peak speed or displacement above the rest noise.
    integral_resolution : float
        How far the integral can be off through the velocity's own resolution alone: the
        velocity step the drive reports in (1 rpm on a drive whose 0x606C is in rpm; 0 for
        a velocity with no visible step) times the duration [position units].
    """

    number: int
    amplitude: float
    peak_velocity: float
    displacement: float
    integrated: float
    moved: bool
    integral_resolution: float = 0.0


@dataclass(frozen=True)
class BumpResult:
    """Outcome of a passed bump test.

    Attributes
    ----------
    pulses : tuple of BumpPulse
        Every pulse in order.
    breakaway_pos, breakaway_neg : float
        Smallest pulse magnitude that moved the axis each way [command units]
        (an upper bound of the breakaway friction).
    speed_threshold : float
        Motion threshold used [velocity units/s].
    position_checked : bool
        False when the displacement was too small to judge against the noise.
    log_path : Path
        ``bump.csv``.
    """

    pulses: tuple[BumpPulse, ...]
    breakaway_pos: float
    breakaway_neg: float
    speed_threshold: float
    position_checked: bool
    log_path: Path

    def as_dict(self) -> dict[str, object]:
        return {
            "breakaway_pos_upper": self.breakaway_pos,
            "breakaway_neg_upper": self.breakaway_neg,
            "speed_threshold": self.speed_threshold,
            "position_checked": self.position_checked,
            "pulses": [p.__dict__ for p in self.pulses],
            "log": self.log_path.name,
        }


@dataclass(frozen=True)
class _Noise:
    speed_threshold: float
    travel_threshold: float


def at_link_rate(settings: BumpSettings, sidbe_fs_hz: object, drive: Drive) -> BumpSettings:
    """``settings`` at the cycle rate the drive's link carries (:meth:`Drive.max_rate_hz`).

    ``[bump] fs_hz`` unset: the link's default rate, as ``sidbe`` picks it. A
    ``[bump] fs_hz`` or ``[sidbe] fs_hz`` beyond the link raises
    :class:`~servobench.errors.UsageError` naming the achievable rate, before
    anything moves.
    """
    from servobench.bench.procedure.excitation import DEFAULT_FS_HZ
    from servobench.drivers.link_budget import drive_rate_hz

    if isinstance(sidbe_fs_hz, int | float):  # other values: [sidbe] is checked in step 2
        drive_rate_hz(float(sidbe_fs_hz), drive, DEFAULT_FS_HZ, "[sidbe] fs_hz")
    return replace(settings, fs_hz=drive_rate_hz(settings.fs_hz, drive, DEFAULT_FS_HZ, "[bump] fs_hz"))


def plan_text(limits: ConfirmedLimits, settings: BumpSettings) -> str:
    """What the bump test does, in one sentence (for ``--dry-run``)."""
    amps = ", ".join(f"{f * limits.max_u:.3g}" for f in settings.fractions)
    return (
        f"bump test: {settings.pulse_s:g} s pulses of +-({amps}) [command units], "
        f"smallest first until the axis moves, at {settings.fs_hz:g} Hz"
    )


def run_bump_test(
    drive: Drive,
    limits: ConfirmedLimits,
    settings: BumpSettings,
    log_path: str | Path,
    *,
    pace: str = "real",
    progress: ProgressCallback | None = None,
) -> BumpResult:
    """Bump-test an open drive; it is enabled here and left stopped and disabled.

    ``settings.fs_hz`` None streams at the link's default rate (:func:`at_link_rate`).

    Raises
    ------
    CommissionRefused
        No motion, wrong direction, or insane feedback.
    """
    log_path = Path(log_path)
    if settings.fs_hz is None:
        settings = at_link_rate(settings, None, drive)
    dt = 1.0 / settings.fs_hz
    total = 2 * len(settings.fractions)
    pulses: list[BumpPulse] = []
    meta = {**_metadata(drive, settings), "pace": pace}
    with ReactiveCycle(drive, dt, pace, log_path, meta) as cycle:
        streamer = _Streamer(drive, cycle)
        try:
            drive.set_cycle(dt)
            drive.enable()
            rest = streamer.run(0, np.zeros(REST_CYCLES))
            noise = _noise(rest, limits)
            breakaway: dict[int, float] = {}
            for direction in (1, -1):
                for i, fraction in enumerate(settings.fractions):
                    pulse = _pulse(streamer, len(pulses) + 1, direction * fraction * limits.max_u,
                                   settings, limits, noise)  # fmt: skip
                    pulses.append(pulse)
                    if progress is not None:
                        progress((0 if direction > 0 else len(settings.fractions)) + i + 1, total)
                    if pulse.moved:
                        breakaway[direction] = abs(pulse.amplitude)
                        break
            drive.stop()
            drive.disable()
        except BaseException as err:
            with contextlib.suppress(DriveError, OSError):
                drive.stop()
            with contextlib.suppress(DriveError, OSError):
                drive.disable()
            reason = "interrupted (Ctrl-C)" if isinstance(err, KeyboardInterrupt) else str(err)
            cycle.finish("incomplete", reason=reason or type(err).__name__)
            raise
        cycle.finish("complete")
    checked = judge(pulses, breakaway, noise, settings, streamer.clock_advanced)
    return BumpResult(tuple(pulses), breakaway[1], breakaway[-1], noise.speed_threshold, checked, log_path)


def _metadata(drive: Drive, settings: BumpSettings) -> dict[str, object]:
    return {"fs": settings.fs_hz, "drive": drive.url.raw, "experiment": "bump test"}


class _Streamer:
    """Cycle the drive on the reactive cyclic engine, keep the arrays of the last segment."""

    def __init__(self, drive: Drive, cycler: ReactiveCycle) -> None:
        self.drive, self.cycler = drive, cycler
        self.writer = cycler.writer
        self.first_t: float | None = None
        self.clock_advanced = False

    def cycle(self, run: int, u: float) -> tuple[float, float, float, float]:
        fb, applied, t = self.cycler.exchange(run, u)
        if self.first_t is None:
            self.first_t = fb.t_s
        elif fb.t_s != self.first_t:
            self.clock_advanced = True
        if not (math.isfinite(fb.velocity) and math.isfinite(fb.position)):
            raise CommissionRefused(
                f"feedback is not finite during the bump test (v={fb.velocity}, x={fb.position})"
            )
        return t, applied, fb.velocity, fb.position

    def run(self, run: int, u: np.ndarray) -> np.ndarray:
        """Stream ``u``; rows ``(t, u, v, x)``."""
        return np.array([self.cycle(run, float(uk)) for uk in u]).reshape(-1, 4)


def _noise(rest: np.ndarray, limits: ConfirmedLimits) -> _Noise:
    v, x = rest[:, 2], rest[:, 3]
    steps = np.abs(np.diff(x))
    quantum = float(steps[steps > 0].min()) if np.any(steps > 0) else 0.0
    speed = max(NOISE_FACTOR * float(np.std(v)), MIN_SPEED_FRACTION * limits.max_v, 1e-12)
    travel = max(NOISE_FACTOR * float(np.std(x)), 2.0 * quantum, 1e-12)
    return _Noise(speed, travel)


def _pulse(
    s: _Streamer,
    number: int,
    amplitude: float,
    settings: BumpSettings,
    limits: ConfirmedLimits,
    noise: _Noise,
) -> BumpPulse:
    span = limits.xmax - limits.xmin
    max_travel = MAX_TRAVEL_FRACTION * span if math.isfinite(span) else math.inf
    rows = []
    x0 = None
    for _ in range(max(1, round(settings.pulse_s * settings.fs_hz))):
        row = s.cycle(number, amplitude)
        rows.append(row)
        x0 = row[3] if x0 is None else x0
        if abs(row[2]) > settings.max_speed_fraction * limits.max_v or abs(row[3] - x0) > max_travel:
            break
    quiet = 0
    for _ in range(max(1, round(settings.rest_s * settings.fs_hz))):
        row = s.cycle(number, 0.0)
        rows.append(row)
        still = abs(row[3] - rows[-2][3]) <= noise.travel_threshold
        quiet = quiet + 1 if still and abs(row[2]) <= noise.speed_threshold else 0
        if quiet >= QUIET_SAMPLES:
            break
    data = np.array(rows)
    return analyse_pulse(number, amplitude, data[:, 0], data[:, 2], data[:, 3], noise)


def analyse_pulse(
    number: int, amplitude: float, t: np.ndarray, v: np.ndarray, x: np.ndarray, noise: _Noise
) -> BumpPulse:
    """Velocity response, displacement and integrated velocity of one pulse and its coast.

    An axis still coasting from the previous pulse is judged by the velocity
    change this pulse made; an axis at rest by the velocity itself.
    """
    at_rest = abs(v[0]) <= noise.speed_threshold
    response = v if at_rest else v - v[0]
    peak = float(response[int(np.argmax(np.abs(response)))])
    displacement = float(x[-1] - x[0])
    integrated = float(np.sum(0.5 * (v[1:] + v[:-1]) * np.diff(t))) if len(t) > 1 else 0.0
    moved = abs(peak) > noise.speed_threshold or (
        at_rest and abs(displacement) > noise.travel_threshold
    )
    # A velocity reported in whole steps (rounded or truncated) is off by up to one step at
    # every sample, the same way while the speed sweeps few steps: bound its integral so.
    resolution = signal_step(v) * float(t[-1] - t[0]) if len(t) > 1 else 0.0
    return BumpPulse(number, float(amplitude), peak, displacement, integrated, moved, resolution)


def judge(
    pulses: list[BumpPulse],
    breakaway: dict[int, float],
    noise: _Noise,
    settings: BumpSettings,
    clock_advanced: bool,
) -> bool:
    """Refuse unless both directions moved the right way with consistent feedback.

    Returns whether the position/velocity consistency could be judged.
    """
    if not clock_advanced:
        raise CommissionRefused(
            "feedback is frozen: the drive's time stamps did not advance during the bump test; "
            "check that the drive streams fresh feedback (PDO mapping / SYNC, polling)"
        )
    for direction, name in ((1, "positive"), (-1, "negative")):
        if direction not in breakaway:
            tried = max(abs(p.amplitude) for p in pulses if np.sign(p.amplitude) == direction)
            raise CommissionRefused(
                f"no motion in the bump test: a {name} command up to {tried:.3g} did not move the axis "
                f"(|v| stayed below {noise.speed_threshold:.3g}); check that the drive is in "
                "torque/current mode and enabled, the brake is released, the axis is free, and the "
                "feedback is live, or raise [bump] fractions if the friction is that high"
            )
    moving = [p for p in pulses if p.moved]
    for p in moving:
        if np.sign(p.peak_velocity) != np.sign(p.amplitude):
            sign = "positive" if p.amplitude > 0 else "negative"
            got = "negative" if p.peak_velocity < 0 else "positive"
            raise CommissionRefused(
                f"wrong direction in the bump test: a {sign} command gave a {got} velocity "
                f"({p.peak_velocity:.3g}); invert the motor/command polarity or the encoder "
                "direction in the drive's configuration so that positive command gives positive "
                "velocity (and rising position), then run again"
            )
    checked = False
    for p in moving:
        scale = max(abs(p.displacement), abs(p.integrated))
        if scale <= POSITION_JUDGE_FACTOR * noise.travel_threshold:
            continue
        if p.integral_resolution > settings.position_tolerance * scale:
            continue  # the velocity's steps alone could account for the tolerance: not judged
        checked = True
        if np.sign(p.displacement) != np.sign(p.integrated):
            raise CommissionRefused(
                f"position runs against velocity in the bump test (dx = {p.displacement:.4g}, "
                f"integral of v = {p.integrated:.4g}); invert the position (encoder) direction "
                "or the velocity sign in the drive's configuration"
            )
        mismatch = max(abs(p.displacement - p.integrated) - p.integral_resolution, 0.0) / scale
        if mismatch > settings.position_tolerance:
            raise CommissionRefused(
                f"position and velocity feedback disagree in the bump test: dx = {p.displacement:.4g} "
                f"but the integral of v is {p.integrated:.4g} (ratio {p.displacement / p.integrated:.3g}); "
                "check the feedback scaling (units, encoder counts per unit, gear ratio) "
                "and that neither signal is frozen"
            )
    return checked
