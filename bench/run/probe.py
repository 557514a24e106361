"""A short first run on an axis with limited travel: a relay on position.

Before the hold loop can be designed, something must be known of the axis.
Where no bump test has told it, the probe finds it out without leaving a
small part of the travel: a relay with hysteresis on position (as relay
auto-tuners do), ``u = +A`` until ``x > x0 + h``, then ``u = -A`` until
``x < x0 - h``, and so on, with ``h`` a tenth of the room around the start
``x0``. Braking with the same ``A`` that accelerated keeps the swing within
about ``3 h`` whatever the axis; the relay also reverses early beyond half of
``max_v``. The level starts small and doubles until the axis swings (a level
that has not moved it beyond the rest noise within :data:`STILL_S`, or has
not reversed within :data:`WAIT_S`, doubles), then :data:`SWITCHES`
reversals are logged and the axis comes to rest at a turn.

The relay's samples are identified by the joint estimator
(:func:`~servobench.bench.identify.joint.identify_joint`): ``M``, ``B`` and
both Coulomb levels, rough but enough to design the hold and the excitation.
Every sample goes to ``probe.csv`` as it is taken (``run`` = relay level, 0
the rest before it), kept on any failure; each command follows from the
sample before it, so the relay runs on
:class:`~servobench.bench.run.reactive.ReactiveCycle` (the cyclic engine's
deadlines, instants and ``t_unc`` at real pace). A relay that runs away (wrong
polarity) or an axis that never swings stops with a one-line error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from servobench.bench.identify.dataset import prepare
from servobench.bench.identify.joint import identify_joint
from servobench.bench.log.io import read_log
from servobench.bench.model.servo import ServoModel
from servobench.bench.run.reactive import ReactiveCycle
from servobench.bench.run.runner import (
    REST_SAMPLES,
    _reason,
    _stop_quietly,
    note_partial_log,
)
from servobench.bench.run.travel import TravelWindow
from servobench.drivers.base import Drive
from servobench.errors import IdentificationError, LimitExceededError, UsageError

#: The probe's log in a run folder.
PROBE_LOG = "probe.csv"
#: Hysteresis of the relay [share of the room around the start].
HYSTERESIS_SHARE = 0.1
#: A swing beyond this share of the room stops the probe (a runaway, or a window too small).
ABORT_SHARE = 0.6
#: The relay reverses early beyond this share of max_v.
SPEED_SHARE = 0.5
#: Reversals logged at the level that swings.
SWITCHES = 8
#: Longest wait for a reversal before the level doubles [s].
WAIT_S = 2.0
#: A level that has not moved the axis beyond the rest noise after this long doubles [s].
STILL_S = 0.3
#: Motion threshold over the position's spread at rest.
NOISE_FACTOR = 6.0
#: Cycles at zero command before the relay (rest and noise).
REST_CYCLES = 100
#: Longest coast to rest after the relay [s].
COAST_S = 2.0
#: First relay level [share of max_u] when the drive sets one.
START_FRACTION = 0.02


@dataclass(frozen=True)
class ProbeResult:
    """What the probe learnt.

    Attributes
    ----------
    model : ServoModel
        The rough model of the axis.
    amplitude : float
        Relay level that made the axis swing [command units].
    x_start : float
        Position at the start [position units].
    noise_std : float
        Velocity noise the identification saw [velocity units/s].
    log_path : Path
    """

    model: ServoModel
    amplitude: float
    x_start: float
    noise_std: float
    log_path: Path

    def as_dict(self) -> dict[str, object]:
        return {**self.model.as_dict(), "relay_amplitude": self.amplitude,
                "noise_std": self.noise_std, "log": self.log_path.name}  # fmt: skip


def probe_start(amplitude: float | None, max_u: float) -> float:
    """The first relay level: a small share of ``max_u``, else a quarter of ``amplitude``."""
    if math.isfinite(max_u):
        return START_FRACTION * max_u
    return (amplitude or 1.0) / 4.0


def run_probe(
    drive: Drive,
    window: TravelWindow,
    fs_hz: float,
    start: float,
    cap: float,
    log_path: str | Path,
    *,
    pace: str = "real",
) -> ProbeResult:
    """Relay-probe an open drive (enabled here, left stopped and disabled) and identify it.

    Raises
    ------
    LimitExceededError
        The relay ran away (wrong polarity) or the Drive layer stopped the axis.
    UsageError
        The axis did not swing up to ``cap``, or its swing cannot be identified.
    """
    log_path = Path(log_path)
    meta = {"fs": fs_hz, "drive": drive.url.raw, "pace": pace, "experiment": "relay probe",
            **drive.log_metadata()}  # fmt: skip
    with ReactiveCycle(drive, 1.0 / fs_hz, pace, log_path, meta) as cycle:
        relay = _Relay(drive, window, 1.0 / fs_hz, cycle)
        try:
            level = relay.session(start, cap)
        except BaseException as err:
            try:
                _stop_quietly(drive)
            finally:
                cycle.finish("incomplete", reason=_reason(err))
                note_partial_log(err, cycle.writer)
            raise
        cycle.finish("complete", relay_amplitude=level)
    return _identify(log_path, level, relay.x0)


def _identify(log_path: Path, level: float, x0: float) -> ProbeResult:
    log = read_log(log_path)
    swing = max(r.run for r in log.runs)  # the level that swung, and its coast
    try:
        data = prepare(replace(log, runs=(log.run(swing),)))
        est = identify_joint(data)
    except IdentificationError as err:
        raise UsageError(
            f"the relay probe could not learn the axis ({err}); probe log kept in {log_path}. "
            "Give the excitation yourself (--amplitude and --freqs) or run with --loop open"
        ) from None
    return ProbeResult(est.model, level, x0, est.noise_std, log_path)


class _Relay:
    """The relay experiment, cycle by cycle, every sample logged."""

    def __init__(self, drive: Drive, window: TravelWindow, dt: float, cycler: ReactiveCycle):
        self.drive, self.window, self.dt, self.cycler = drive, window, dt, cycler
        self.writer = cycler.writer
        self.x0 = math.nan
        self.still = 0.0  # displacement that counts as motion [position units]

    def cycle(self, run: int, u: float) -> tuple[float, float]:
        fb, _, _ = self.cycler.exchange(run, u)
        if not (math.isfinite(fb.position) and math.isfinite(fb.velocity)):
            raise LimitExceededError(f"non-finite feedback in the relay probe (x={fb.position}, v={fb.velocity})")
        return fb.position, fb.velocity

    def session(self, start: float, cap: float) -> float:
        """Rest, relay at rising levels until the axis swings, coast; the level that swung."""
        self.drive.set_cycle(self.dt)
        self.drive.enable()
        xs = np.array([self.cycle(0, 0.0)[0] for _ in range(REST_CYCLES)])
        self.x0 = float(np.median(xs))
        steps = np.abs(np.diff(xs))
        quantum = float(steps[steps > 0].min()) if np.any(steps > 0) else 0.0
        self.still = max(NOISE_FACTOR * float(np.std(xs)), 2.0 * quantum)
        room = self.window.room(self.x0)
        if not room > 0:
            raise UsageError(
                f"the axis is at {self.x0:.4g}, at or outside the edge of its travel "
                f"{self.window.describe()}: the relay probe needs room on both sides; move it "
                "towards the middle"
            )
        level, run = min(start, cap), 1
        while not self.relay(run, level, HYSTERESIS_SHARE * room, ABORT_SHARE * room):
            if level >= cap:
                raise UsageError(
                    f"the axis did not swing in the relay probe up to ±{cap:.4g}; probe log kept in "
                    f"{self.writer.path}. Check that it is free and the drive in torque mode, or "
                    "raise the amplitude cap (max_u, --max-amplitude)"
                )
            level, run = min(2.0 * level, cap), run + 1
        self.coast(run)
        self.drive.stop()
        self.drive.disable()
        return level

    def relay(self, run: int, level: float, h: float, abort: float) -> bool:
        """One relay level; True when it logged :data:`SWITCHES` reversals."""
        vmax = SPEED_SHARE * self.drive.limits.max_velocity
        sign, switches, waited = 1.0, 0, 0
        x, v = self.cycle(run, sign * level)
        x_level, moved = x, 0.0
        while switches < SWITCHES or v * sign < 0:  # the last swing is braked to its turn
            turn = (sign > 0 and (x > self.x0 + h or v > vmax)) or (
                sign < 0 and (x < self.x0 - h or v < -vmax)
            )
            if turn and switches < SWITCHES:
                sign, switches, waited = -sign, switches + 1, 0
            if abs(x - self.x0) > abort:
                raise LimitExceededError(
                    f"axis stopped: the relay probe swung to {x:.4g}, beyond {ABORT_SHARE:.0%} of the "
                    f"room around {self.x0:.4g}; probe log kept in {self.writer.path}. Check that "
                    "positive command gives positive velocity and rising position, or widen xmin/xmax"
                )
            waited += 1
            moved = max(moved, abs(x - x_level))
            if waited * self.dt > WAIT_S or (switches == 0 and waited * self.dt > STILL_S
                                             and moved <= max(self.still, 1e-3 * h)):  # fmt: skip
                return False
            x, v = self.cycle(run, sign * level)
        return True

    def coast(self, run: int) -> None:
        quiet = 0
        for _ in range(max(1, round(COAST_S / self.dt))):
            _, v = self.cycle(run, 0.0)
            quiet = quiet + 1 if v == 0.0 else 0
            if quiet >= REST_SAMPLES:
                return
