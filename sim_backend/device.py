"""The simulated drive: a :class:`~servobench.sim_backend.physics.plant.Plant` behind a power stage.

:class:`SimulatedDevice` is what every transport serves (and what ``sim://``
wraps in-process): a lock-step drive that samples its feedback and then
applies the latest command for one control cycle each time it is clocked
(a SYNC, a Modbus feedback read, a serial feedback query), a power state
(disabled / enabled / quick stop / fault), a command limit like CiA 402's
max torque 0x6072, and a drive-side watchdog that trips when the host falls
silent.

Clock modes
-----------
``clock="lockstep"`` (the default; ``sim://`` unless ``clock=real``): the
drive is clocked once per control cycle, exact zero-order hold, its drive
clock counting clocked cycles times the cycle. For algorithm tests: the
host's timing never reaches the data.

``clock="real"`` (served drives by default, ``serve-sim --clock real``, and
``sim://?clock=real``): the drive does not wait for its host. Its physics
integrates wall-clock time (:class:`~servobench.sim_backend.physics.realtime.TimedPlant`),
enabled or not. Feedback is sampled when the SYNC or the read is handled:
every call first integrates the plant from the last integration instant up
to now with the command in force, then measures. The command in force is the
last one received: a new command first integrates up to its arrival with the
old one, then latches. A power stage that goes off removes the torque at
that instant. The drive clock (:attr:`DeviceSample.t_s`) is the drive's own
free-running clock: the wall time [s] since the host session began, read at
the instant each sample is taken (not a cycle count); the transports encode
it at their register's resolution (CiA 402 0x1013: UNSIGNED32 microseconds,
wrapping).

A control tick of its own (``clock="real"``, ``tick_s > 0``)
------------------------------------------------------------
``sim://?clock=real&tick=S``, ``serve-sim --tick S``: the drive runs its
physics on its own tick grid, asynchronous to the host, as a real drive's
control loop does (:mod:`servobench.sim_backend.drive_tick`): tick instants
``phase + k * S`` on the device's wall clock, the phase drawn uniformly in
``[0, S)`` when the device is made (from the plant's ``seed`` if it has
one). A command takes force at the first tick strictly after its arrival
(the request's instant) and is held until the tick at which a later one
takes force; of two commands that arrive between the same two ticks the
later one wins (the plant's ``delay`` effect adds on top). A read returns
the sample of the last tick at or before its instant: the plant measured
once at that tick (one noise draw), so every read within one tick returns
the same velocity, position and time stamp, the stamp being that tick's
instant on the drive clock (the drive clock then stands at 0 at the tick a
session began in, so the stamps are whole ticks). Power-stage changes still
remove the torque at the instant they happen, and :meth:`~SimulatedDevice.true_state`
is the state now. :meth:`~SimulatedDevice.timing` is the drive's record of
its timing (:class:`~servobench.sim_backend.drive_tick.TimingRecord`). With
``tick_s == 0`` (the default) nothing of this applies. Lockstep drives have
no tick of their own (a tick needs ``clock="real"``).

A drive clock that drifts (``clock="real"``, ``drift_ppm != 0``)
----------------------------------------------------------------
``sim://?clock=real&drift=PPM``, ``serve-sim --drift PPM``: the drive's
crystal runs ``PPM`` parts per million fast (negative: slow) against the
host's clock, as every real drive's does by some 10-100 ppm. Its clock
reads ``rate = 1 + PPM * 1e-6`` drive seconds per wall-clock second: the
time stamps step by that much more, and with a tick ``S`` (S on the drive's
own clock) the ticks fall ``S / rate`` apart on the wall clock, so their
phase against the host's cycle slides along the run. The physics stays in
wall-clock time. Default 0: the host's rate.

Wall-clock time in lockstep (served drives)
-------------------------------------------
A real axis does not wait for the host: after a quick stop it coasts down
whether anybody polls it or not. A lockstep device made with
``wall_clock=True`` (``serve-sim --clock lockstep``) therefore integrates
wall-clock time while its power stage is off (disabled, quick stop, fault):
every call first advances the plant by the time since it was last
integrated, with zero command, so the axis coasts down as a real one does,
polled or not. (The drive clock counts clocked cycles: it stands while
nobody clocks the drive.) While the axis is enabled the drive stays
lock-step (one clock per cycle, exact ZOH), so a host that falls behind on a
loaded machine does not change the data; its silence is still bounded by
the watchdog, which trips in wall-clock time and is integrated (with the
command that was applied) up to the moment it tripped. A new host session
(:meth:`SimulatedDevice.begin_session`) integrates whatever time has passed.
With ``wall_clock=False`` (in-process lockstep ``sim://``): pure lock-step.

Sessions
--------
:meth:`SimulatedDevice.begin_session` is what a served transport calls when
a host session starts (a TCP connection when no other is open, a pty opened
by a client, a CANopen host's first NMT command): the drive clock restarts
at 0 and the cycle counter with it, the latched command is dropped, an
enabled axis is disabled, and the axis keeps its position (after coasting).
A latched fault stays latched, as on a real drive; so do the watchdog and
cycle settings.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from enum import Enum

import numpy as np

from servobench.errors import DriveConfigError, DriveFaultError
from servobench.sim_backend.drive_tick import (
    TickGrid,
    TimingRecord,
    check_drift,
    draw_phase,
    drift_from_url,
    tick_from_url,
)
from servobench.sim_backend.physics.plant import Plant, PlantParams
from servobench.sim_backend.physics.realtime import TimedPlant

#: Fault code the watchdog raises: CiA 301/402 "heartbeat / life guard error".
WATCHDOG_FAULT = 0x8130
#: Fault code of a generic drive fault injected by tests or the fault injector.
GENERIC_FAULT = 0x1000
#: Most integration steps of one catch-up; longer idle spans take longer steps
#: (the base plant is exact under zero-order hold for any step).
MAX_CATCH_UP_STEPS = 100_000
#: A watchdog-thread wake-up this late means the simulator itself was not running [s].
STALL_S = 0.05
#: Power states in which the watchdog is checked by default (an axis with torque).
TORQUE_STATES = frozenset({"enabled", "quick_stop"})
#: Clock modes (see the module doc): one clock per cycle, or wall-clock time.
LOCKSTEP = "lockstep"
REAL = "real"
CLOCK_MODES = (LOCKSTEP, REAL)


def clock_counts(t_s: float, resolution_s: float) -> int:
    """The drive clock ``t_s`` [s] as a counter ticking every ``resolution_s`` [s] (whole ticks elapsed).

    A hardware counter reads the ticks that have elapsed (it truncates); the
    tolerance of 1e-6 tick keeps a lockstep clock, an exact multiple of the
    cycle, on its tick despite rounding in ``k * cycle_s``.
    """
    return math.floor(t_s / resolution_s + 1e-6)


class PowerState(Enum):
    """Power stage of the simulated drive."""

    DISABLED = "disabled"
    ENABLED = "enabled"
    QUICK_STOP = "quick_stop"
    FAULT = "fault"


@dataclass(frozen=True)
class DeviceSample:
    """Feedback of one cycle: plant time [s], velocity, position, power state, fault code."""

    t_s: float
    velocity: float
    position: float
    state: PowerState
    fault_code: int


class SimulatedDevice:
    """A simulated servo drive, thread-safe, clocked once per control cycle.

    Parameters
    ----------
    params : PlantParams
        The plant.
    cycle_s : float
        Control cycle [s] until the host sets another with :meth:`set_cycle`.
    max_command : float
        Drive-side command limit [command units] (like 0x6072).
    watchdog_s : float or None
        Host silence after which an enabled drive faults and removes torque.
    clock : callable
        Wall clock for the watchdog and the wall-clock integration [s],
        ``time.monotonic`` by default.
    wall_clock : bool
        Integrate the time the host leaves unpolled (see the module doc);
        False: pure lock-step.
    watchdog_in_every_state : bool
        Check the watchdog whatever the power state, as ODrive firmware 0.5
        does (``Firmware/MotorControl/axis.cpp``, ``watchdog_check``); False:
        only while the axis has torque (enabled or quick stop).
    clock_mode : str
        ``"lockstep"`` or ``"real"`` (see the module doc); ``"real"`` implies
        ``wall_clock``.
    tick_s : float
        The drive's own control tick [s] (``"real"`` only; see the module
        doc); 0: none, the drive samples and acts at each request's instant.
    drift_ppm : float
        The drive clock's drift against the wall clock [ppm] (``"real"`` only; see the
        module doc); 0: none.
    """

    def __init__(
        self,
        params: PlantParams,
        *,
        cycle_s: float = 1e-3,
        max_command: float = math.inf,
        watchdog_s: float | None = None,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: bool = False,
        watchdog_in_every_state: bool = False,
        clock_mode: str = LOCKSTEP,
        tick_s: float = 0.0,
        drift_ppm: float = 0.0,
    ) -> None:
        if clock_mode not in CLOCK_MODES:
            raise ValueError(f"clock mode must be one of {', '.join(CLOCK_MODES)}, got {clock_mode!r}")
        if not (math.isfinite(tick_s) and tick_s >= 0):
            raise DriveConfigError(
                f"drive tick must be a finite number of seconds >= 0, got {tick_s!r}"
            )
        if tick_s > 0 and clock_mode != REAL:
            raise DriveConfigError(
                f"a drive tick (tick={tick_s:g}) needs clock=real (serve-sim --clock real), "
                f"not clock={clock_mode}: a lock-step drive is clocked by its host"
            )
        drift_ppm = check_drift(drift_ppm)
        if drift_ppm != 0 and clock_mode != REAL:
            raise DriveConfigError(
                f"a drifting drive clock (drift={drift_ppm:g}) needs clock=real (serve-sim --clock "
                f"real), not clock={clock_mode}: a lock-step drive runs on its host's clock"
            )
        self.params = params
        #: The drive clock's seconds per wall-clock second (1 + its drift).
        self.clock_rate = 1.0 + drift_ppm * 1e-6
        self.plant = Plant(params, compiled=False)  # a drive's loop never waits on a compile
        self.cycle_s = float(cycle_s)
        self.max_command = float(max_command)
        self.watchdog_s = watchdog_s
        self.clock_mode = clock_mode
        self.realtime = clock_mode == REAL
        self.wall_clock = wall_clock or self.realtime
        self.watchdog_in_every_state = watchdog_in_every_state
        self._clock = clock
        self._lock = threading.RLock()
        self._k = 0  # cycles clocked since the clock was last rebased
        self._t_base_s = 0.0  # drive clock at the last rebase [s]
        self._t_s = 0.0
        self._wall_due = clock()  # wall time up to which the plant has been integrated
        self._pinned: float | None = None  # the instant of the request being handled (instant())
        #: The instant [s, wall clock] of the next event a server handles late at its own
        #: instant (an EtherCAT SYNC0), else None: whatever runs outside a request (the state
        #: report, a watchdog) integrates the plant no further than it, so the event finds
        #: the plant as it stood then, as a drive's hardware event does.
        self.hold_before_s: float | None = None
        self._wall_base = self._wall_due  # wall time at which the drive clock read _t_base_s
        #: The plant in wall-clock time (``clock="real"`` only).
        self.timed = TimedPlant(self.plant, self._wall_due, self.cycle_s) if self.realtime else None
        #: The drive's own tick grid (``tick_s > 0``), else None.
        self.tick = (
            TickGrid(float(tick_s), draw_phase(tick_s, params.seed), self.clock_rate) if tick_s > 0 else None
        )
        self._timing = TimingRecord(tick_s, self.tick.phase_s if self.tick else 0.0, self.clock_rate)
        self._read_pinned = False  # a read of the request being handled was counted
        if self.tick is not None:  # the plant stood in its initial state at the last tick
            self._tick_k = self._tick_base = self.tick.index_at(self._wall_due)
            self._tick_vx = self.timed.measure()  # the sample of tick _tick_k
            self._wall_base = self.tick.instant(self._tick_base)
        self._command = 0.0
        #: Host sessions begun (:meth:`begin_session`).
        self.sessions = 0
        #: Wall-clock time integrated while the host was silent [s].
        self.idle_s = 0.0
        self.state = PowerState.DISABLED
        #: Called as ``listener(state, fault_code)`` on every power-state change, under the lock.
        self.listeners: list[Callable[[PowerState, int], None]] = []
        self.fault_code = 0
        self.fault_reason = ""
        self.last_host_activity = clock()
        #: False: only :meth:`feed_life_signal` feeds the watchdog (a CANopen heartbeat
        #: consumer, CiA 301 7.2.8.3.2.4), not the host's commands and requests.
        self.activity_feeds_watchdog = True
        self.watchdog_trips = 0
        self.frozen_feedback: DeviceSample | None = None

    # ------------------------------------------------------------ host side
    @contextlib.contextmanager
    def instant(self, at_s: float | None = None) -> Iterator[None]:
        """Handle one request at one instant: the wall clock stands still inside (``real``).

        A request that carries a command and asks for feedback (a Modbus FC23,
        a SYNC that applies the synchronous RPDO before it) is handled at the
        instant it arrived, as a drive does: the command latches and the
        feedback is sampled at that same instant, however long the simulator
        takes over it. ``at_s``: that instant on the device's clock (a
        hardware event the simulator handles late, e.g. an EtherCAT SYNC0),
        default now; never before the instant the plant has been integrated
        up to. Holds the device lock throughout; nests.
        """
        with self._lock:
            if self._pinned is not None:
                yield
                return
            self._pinned = self._clock() if at_s is None else float(at_s)
            self._read_pinned = False
            try:
                yield
            finally:
                self._pinned = None

    def _now(self) -> float:
        return self._clock() if self._pinned is None else self._pinned

    def feed(self) -> None:
        """Note host activity (any valid message counts, unless :attr:`activity_feeds_watchdog`
        is False)."""
        if self.activity_feeds_watchdog:
            self.last_host_activity = self._clock()

    def feed_life_signal(self) -> None:
        """The host's life signal (a heartbeat): it always feeds the watchdog."""
        self.last_host_activity = self._clock()

    def set_cycle(self, cycle_s: float) -> None:
        """Set the control cycle [s]; the drive clock goes on from where it stands."""
        with self._lock:
            if not cycle_s > 0:
                raise ValueError("cycle must be > 0 s")
            self._catch_up()
            if self.timed is None:
                self._rebase(self._t_s)
            else:  # the free-running clock goes on; sub-steps no longer than the new cycle
                self._k = 0
                self.timed.max_step_s = float(cycle_s)
            self.cycle_s = float(cycle_s)

    def begin_session(self) -> None:
        """A host session starts: clock at 0, command dropped, torque off (see the module doc)."""
        with self._lock:
            self._catch_up(force=True)
            self.sessions += 1
            self._rebase(0.0)
            self._command = 0.0
            self.feed()
            if self.state in (PowerState.ENABLED, PowerState.QUICK_STOP):
                self._set_state(PowerState.DISABLED)

    def set_watchdog(self, watchdog_s: float | None) -> None:
        with self._lock:
            self.watchdog_s = watchdog_s
            self.feed()

    def set_command(self, u: float) -> None:
        """Latch the command applied from the next cycle on (clamped to ``max_command``)."""
        with self._lock:
            self._catch_up()
            self.feed()
            if not math.isfinite(u):
                u = 0.0
            self._command = min(max(float(u), -self.max_command), self.max_command)
            if self.state is not PowerState.ENABLED:
                return
            if self.tick is not None:  # from the first tick after its arrival
                self.timed.latch_at(self.tick.instant(self._tick_k + 1), self._command)
                self._timing.command(self._tick_k + 1, self._command)
                return
            self._timing.command(0, self._command)
            if self.timed is not None:
                self.timed.latch(self._wall_due, self._command)

    @property
    def command(self) -> float:
        """Command the power stage applies now (0 unless enabled)."""
        return self._command if self.state is PowerState.ENABLED else 0.0

    def enable(self) -> None:
        with self._lock:
            self._catch_up()
            self.feed()
            if self.state is PowerState.FAULT:
                raise DriveFaultError(
                    f"drive in fault 0x{self.fault_code:04X}: {self.fault_reason}", self.fault_code
                )
            self._command = 0.0
            self._set_state(PowerState.ENABLED)

    def disable(self) -> None:
        with self._lock:
            self._catch_up()
            self.feed()
            self._command = 0.0
            if self.state is not PowerState.FAULT:
                self._set_state(PowerState.DISABLED)

    def quick_stop(self) -> None:
        """Remove the command; friction brings the axis to rest."""
        with self._lock:
            self._catch_up()
            self.feed()
            self._command = 0.0
            if self.state is PowerState.ENABLED:
                self._set_state(PowerState.QUICK_STOP)

    def fault(self, code: int = GENERIC_FAULT, reason: str = "injected fault") -> None:
        """Enter the fault state: torque off until :meth:`reset_fault`."""
        with self._lock:
            self._catch_up()
            self._fault_now(code, reason)

    def _fault_now(self, code: int, reason: str) -> None:
        """Fault at the instant the plant has been integrated up to."""
        with self._lock:
            self._command = 0.0
            self.fault_code = int(code)
            self.fault_reason = reason
            self._set_state(PowerState.FAULT)

    def reset_fault(self) -> None:
        with self._lock:
            self.feed()
            if self.state is PowerState.FAULT:
                self.fault_code = 0
                self.fault_reason = ""
                self._set_state(PowerState.DISABLED)

    def _set_state(self, state: PowerState) -> None:
        changed = state is not self.state
        self.state = state
        if self.timed is not None and changed:  # the power stage switches at this instant
            self.timed.cut(self._wall_due)
        if changed:
            for listener in self.listeners:
                listener(state, self.fault_code)

    # --------------------------------------------------------------- clocking
    def sample(self) -> DeviceSample:
        """Feedback at the current cycle start (``real``: now), without clocking the plant."""
        with self._lock:
            self._catch_up()
            if self.frozen_feedback is not None:
                return self.frozen_feedback
            if self.timed is not None:
                return self._sample_now()
            v, x = self.plant._measure(
                np.array([self.plant.state.v]), np.array([self.plant.state.x])
            )
            self._note_read()
            return DeviceSample(self._t_s, float(v[0]), float(x[0]), self.state, self.fault_code)

    def step(self) -> DeviceSample:
        """One cycle: sample feedback at ``t_k``, then hold the command until ``t_{k+1}``.

        ``real``: sample the plant now (integrated up to now); it moves on by itself.
        """
        with self._lock:
            self._catch_up()
            if self.timed is not None:
                self._k += 1
                return self.frozen_feedback or self._sample_now()
            v, x = self.plant.step_block(np.array([self.command]), self.cycle_s)
            self._note_read()
            sample = DeviceSample(self._t_s, float(v[0]), float(x[0]), self.state, self.fault_code)
            self._advance(1)
            self._wall_due = self._clock() + self.cycle_s
            return self.frozen_feedback or sample

    def exchange(self, u: float) -> DeviceSample:
        """Latch ``u`` and clock one cycle; return the feedback sampled before ``u`` acts.

        ``real``: both at one instant (:meth:`instant`).
        """
        with self.instant():
            self.set_command(u)
            return self.step()

    def exchange_block(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Many cycles at once: ``(t_s, v, x)`` arrays, one row per cycle (``real``: one exchange each)."""
        if self.timed is not None:
            rows = [self.exchange(float(uk)) for uk in np.asarray(u, dtype=float)]
            return (np.array([r.t_s for r in rows]), np.array([r.velocity for r in rows]),
                    np.array([r.position for r in rows]))  # fmt: skip
        with self._lock:
            self._catch_up()
            self.feed()
            u = np.clip(np.asarray(u, dtype=float), -self.max_command, self.max_command)
            if self.state is not PowerState.ENABLED:
                u = np.zeros_like(u)
            if u.size:
                self._command = float(u[-1])
            self._timing.exchanges(u.size)
            t = self._t_s + self.cycle_s * np.arange(u.size)
            v, x = self.plant.step_block(u, self.cycle_s)
            self._advance(u.size)
            self._wall_due = self._clock() + self.cycle_s
            return t, v, x

    def true_state(self) -> tuple[float, float, float]:
        """``(t_s, v, x)``: drive clock [s] and plant state now, unmeasured (no noise drawn).

        ``real``: integrated up to now; lockstep: as of the last clocked cycle
        (after any wall-clock catch-up of an idle axis).
        """
        with self._lock:
            self._catch_up()
            if self.timed is not None:
                self._t_s = self._drive_clock_at(self._wall_due)
            return float(self._t_s), float(self.plant.state.v), float(self.plant.state.x)

    def _sample_now(self) -> DeviceSample:
        """``real``: the measurement of the plant as integrated up to now, on the drive clock.

        With a tick: the measurement taken at the last tick, stamped with its instant.
        """
        if self.tick is not None:
            v, x = self._tick_vx
            self._t_s = self._t_base_s + (self._tick_k - self._tick_base) * self.tick.tick_s
            self._note_read(self._tick_k)
            return DeviceSample(self._t_s, v, x, self.state, self.fault_code)
        v, x = self.timed.measure()
        self._t_s = self._drive_clock_at(self._wall_due)
        self._note_read()
        return DeviceSample(self._t_s, v, x, self.state, self.fault_code)

    def _note_read(self, tick: int = 0) -> None:
        """Enter a read in the timing record (one per request: :meth:`instant`)."""
        counted = self._pinned is None or not self._read_pinned
        if self._pinned is not None:
            self._read_pinned = True
        self._timing.read(tick, counted)

    def timing(self) -> dict[str, float | int]:
        """The drive's record of its timing: see :meth:`.drive_tick.TimingRecord.as_dict`."""
        with self._lock:
            return self._timing.as_dict()

    def _drive_clock_at(self, wall_s: float) -> float:
        """The drive clock [s] at the wall instant ``wall_s`` (its rate taken in); the inverse of
        :meth:`wall_instant_of`."""
        return self._t_base_s + (wall_s - self._wall_base) * self.clock_rate

    def wall_instant_of(self, t_s: float) -> float:
        """The instant [s, the device's wall clock] the drive clock read ``t_s`` at (``real``)."""
        with self._lock:
            return self._wall_base + (t_s - self._t_base_s) / self.clock_rate

    def _advance(self, n: int) -> None:
        self._k += n
        self._t_s = self._t_base_s + self._k * self.cycle_s

    def _rebase(self, t_s: float) -> None:
        """Let the drive clock stand at ``t_s`` and count cycles from there."""
        self._k = 0
        self._t_base_s = self._t_s = float(t_s)
        if self.timed is None:
            self._wall_due = self._clock()
        self._wall_base = self._wall_due
        if self.tick is not None:  # the clock reads t_s at the last tick: stamps are whole ticks
            self._tick_base = self._tick_k
            self._wall_base = self.tick.instant(self._tick_k)

    def _catch_up(self, until: float | None = None, force: bool = False) -> None:
        """Integrate the wall-clock time the host left unpolled (``wall_clock`` devices only).

        Up to ``until`` (default now), when the axis is not enabled (or at any
        time with ``force``); the power stage applies :attr:`command` over it.
        ``real`` devices integrate in every state, with the command in force.
        """
        if self.timed is not None:
            now = self._now() if until is None else until
            if until is None and self._pinned is None and self.hold_before_s is not None:
                now = min(now, self.hold_before_s)  # an event still to run lies before now
            if now > self._wall_due:
                if self.tick is not None:
                    self._pass_tick(now)
                span_s = self.timed.advance_to(now)
                self._wall_due = now
                if self.state is not PowerState.ENABLED:
                    self.idle_s += span_s
            return
        if not self.wall_clock or (self.state is PowerState.ENABLED and not force):
            return
        now = self._clock() if until is None else until
        lag_s = now - self._wall_due
        if lag_s <= 0:
            return
        n = min(MAX_CATCH_UP_STEPS, max(1, math.ceil(lag_s / self.cycle_s - 1e-9)))
        if self.command != 0.0 or self.plant.state.v != 0.0:
            self.plant.step_block(np.full(n, self.command), lag_s / n)
        self._wall_due = now
        self.idle_s += lag_s

    def _pass_tick(self, now: float) -> None:
        """Tick: measure the plant at the last tick up to ``now`` if the integration passes it."""
        k = self.tick.index_at(now)
        t_k = min(self.tick.instant(k), now)
        if k != self._tick_k and t_k >= self.timed.t_s:
            self.timed.advance_to(t_k)
            self._tick_k, self._tick_vx = k, self.timed.measure()

    # --------------------------------------------------------------- watchdog
    def check_watchdog(self) -> bool:
        """Trip the watchdog if the host has been silent too long; return whether it tripped."""
        with self._lock:
            if self.watchdog_s is None or self.state is PowerState.FAULT:
                return False
            if not self.watchdog_in_every_state and self.state.value not in TORQUE_STATES:
                return False
            silent = self._clock() - self.last_host_activity
            if silent <= self.watchdog_s:
                return False
            self._catch_up(until=self.last_host_activity + self.watchdog_s, force=True)
            self.watchdog_trips += 1
            self._fault_now(
                WATCHDOG_FAULT, f"host silent for {silent:.3f} s (watchdog {self.watchdog_s} s)"
            )
            return True

    def excuse_stall(self, stall_s: float) -> None:
        """The simulator stalled ``stall_s`` [s]: that time does not count as host silence."""
        with self._lock:
            self.last_host_activity = min(self.last_host_activity + stall_s, self._clock())

    @property
    def is_stopped(self) -> bool:
        """True when no torque is applied and the axis is at rest."""
        with self._lock:
            self._catch_up()
            return self.command == 0.0 and self.plant.state.v == 0.0


class WatchdogThread(threading.Thread):
    """Polls :meth:`SimulatedDevice.check_watchdog` every ``period_s`` until stopped.

    A simulator process that was not scheduled for a while (a loaded machine)
    has not read the requests that arrived meanwhile; a wake-up later than
    :data:`STALL_S` after the previous one therefore shifts the host's last
    activity by the stall instead of checking, so the drive does not blame
    the host for its own stall (a host that really went silent trips the
    watchdog at the next check that follows an on-time wake-up).
    """

    def __init__(self, device: SimulatedDevice, period_s: float = 0.01) -> None:
        super().__init__(name="sim-watchdog", daemon=True)
        self.device = device
        self.period_s = period_s
        self._stop_event = threading.Event()

    def run(self) -> None:
        last = time.monotonic()
        while not self._stop_event.wait(self.period_s):
            now = time.monotonic()
            if now - last > max(STALL_S, 5 * self.period_s):
                self.device.excuse_stall(now - last - self.period_s)
            else:
                self.device.check_watchdog()
            last = now

    def stop(self) -> None:
        self._stop_event.set()


def device_from_url(url: str, **kwargs: object) -> SimulatedDevice:
    """A :class:`SimulatedDevice` for a ``sim://`` URL (plant keys, ``max_u``, ``clock``, ``tick``,
    ``drift``).

    A ``clock_mode`` keyword wins over the URL's ``clock`` key, a ``tick_s``
    keyword over its ``tick`` key, a ``drift_ppm`` keyword over its ``drift`` key.
    """
    from servobench.drivers.url import parse_drive_url
    from servobench.sim_backend.simurl import plant_from_url

    parsed = parse_drive_url(url)
    if parsed.scheme != "sim":
        from servobench.errors import DriveConfigError

        raise DriveConfigError(f"expected a sim:// URL, got {url!r}")
    params = plant_from_url(parsed)
    max_u = parsed.get_float("max_u", math.inf)
    kwargs.setdefault("clock_mode", clock_mode_from_url(parsed))
    kwargs.setdefault("tick_s", tick_from_url(parsed))
    kwargs.setdefault("drift_ppm", drift_from_url(parsed))
    return SimulatedDevice(params, max_command=max_u, **kwargs)  # type: ignore[arg-type]


def clock_mode_from_url(url, default: str = LOCKSTEP) -> str:
    """The ``clock`` key of a parsed ``sim://`` URL: ``lockstep`` or ``real`` (else ``default``)."""
    from servobench.errors import DriveConfigError

    mode = url.get_str("clock", default)
    if mode not in CLOCK_MODES:
        raise DriveConfigError(f"sim clock must be 'lockstep' or 'real', got {mode!r}")
    return mode
