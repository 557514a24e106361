"""``sim://`` -- the simulated DC servo with friction, in-process.

``sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4&noise=0.001&pace=fast`` (see
:mod:`servobench.sim_backend.simurl` for every key).

``clock=lockstep`` (default): the drive is clocked once per exchange, exact
zero-order hold; its time stamps are its cycle count times the cycle period.
``pace=real`` paces each cycle to wall-clock time like a real drive;
``pace=fast`` (default) runs as fast as the host asks, and supports block
exchange for batch work.

``clock=real``: the drive does not wait for the host, as a real axis
(:mod:`servobench.sim_backend.device`): its physics integrates wall-clock
time, each exchange samples the plant when it is handled and then latches
the command, and its time stamps are its free-running clock (wall time
since the drive was opened) at each sample. :attr:`realtime` is True, so
the runner paces it; there is no block exchange. ``tick=S`` gives it a
control tick of its own (it samples and acts only at its ticks,
:mod:`servobench.sim_backend.device`).

Drive-side position hold: with ``pos_kp``, ``pos_ki`` or ``pos_kd`` in the
URL the simulated drive has its own position loop -- the served CiA 402
drive's (:mod:`servobench.sim_backend.servers.canopen.position_loop`), the keys
not given from the plant as there -- and
:attr:`~servobench.drivers.base.Drive.supports_drive_hold` is true. While it
holds ``x_ref`` (:meth:`~servobench.drivers.base.Drive.hold_position`), each
cycle applies, from the feedback sampled at the cycle start::

    u = kp (x_ref - x) + ki sum((x_ref - x) dt) - kd v + offset

limited to ``max_u``, ``offset`` being the host's command; ``Feedback.applied``
reports the total applied over the previous cycle. Gains are in plant units
(command units per position unit, per position unit and second, per velocity
unit).
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np

from servobench.drivers.base import BlockFeedback, Drive, DriveInfo, Feedback
from servobench.errors import DriveConfigError, DriveFaultError
from servobench.sim_backend.device import REAL, PowerState, SimulatedDevice, clock_mode_from_url
from servobench.sim_backend.drive_tick import drift_from_url, tick_from_url
from servobench.sim_backend.servers.canopen.position_loop import (
    Gains,
    PositionLoop,
    gains_from_keys,
)
from servobench.sim_backend.simurl import plant_from_url, sim_query_keys, units_from_url

#: Keys of the simulated drive's own position loop (those of the served CiA 402 drive).
HOLD_KEYS = ("pos_kp", "pos_ki", "pos_kd")


class SimDrive(Drive):
    """The simulated drive of :mod:`sim_backend`, driven in-process."""

    query_keys = sim_query_keys() | frozenset(HOLD_KEYS)
    drive_clock = True

    def __init__(self, url) -> None:
        super().__init__(url)
        pace = self.url.get_str("pace", "fast")
        if pace not in ("fast", "real"):
            raise DriveConfigError(f"sim pace must be 'fast' or 'real', got {pace!r}")
        clock_mode = clock_mode_from_url(self.url)
        #: The device integrates wall-clock time (``clock=real``): nothing to pace here.
        self.real_clock = clock_mode == REAL
        self.realtime = pace == "real" or self.real_clock
        self.supports_block = not self.realtime
        given = {k: self._gain(k) for k in HOLD_KEYS if k in self.url.query}
        plant_url = replace(self.url, query={k: v for k, v in self.url.query.items() if k not in HOLD_KEYS})
        self.device = SimulatedDevice(
            plant_from_url(plant_url),
            clock_mode=clock_mode,
            tick_s=tick_from_url(self.url),
            drift_ppm=drift_from_url(self.url),
        )
        p = self.device.params
        self.hold_gains: Gains | None = gains_from_keys(given, p.M, p.B) if given else None
        self.supports_drive_hold = self.hold_gains is not None
        signal_units = units_from_url(plant_url)
        self.units = {"u": signal_units.u, "v": signal_units.v, "x": signal_units.x}
        self._t0_wall: float | None = None
        self._loop: PositionLoop | None = None
        self._x_ref = 0.0
        self._applied = 0.0  # total command of the last held cycle

    def _gain(self, key: str) -> float:
        value = self.url.get_float(key)
        if value is None or not value >= 0:
            raise DriveConfigError(f"sim position loop gain {key}={self.url.query[key]!r} must be >= 0")
        return value

    def log_metadata(self) -> dict[str, str]:
        """The base lines, and the gains of the drive's own position loop when it has one."""
        gains = {} if self.hold_gains is None else self.hold_gains.as_dict()
        return {**super().log_metadata(), **{k: format(v, ".10g") for k, v in gains.items()}}

    def _open(self) -> None:
        self._t0_wall = None
        if self.real_clock:  # a new host session: the drive clock starts at 0 now
            self.device.begin_session()

    def _close(self) -> None:
        self.device.disable()

    def _configure_watchdog(self, timeout_s: float) -> None:
        self.device.set_watchdog(timeout_s)

    def _set_cycle(self, period_s: float) -> None:
        self.device.set_cycle(period_s)

    def _enable(self) -> None:
        self.device.enable()

    def _disable(self) -> None:
        self._loop = None
        self.device.disable()

    def _quick_stop(self) -> None:
        self._loop = None
        self.device.quick_stop()

    def _hold_position(self, x_ref: float) -> None:
        assert self.hold_gains is not None
        self._applied = self.device.command
        self._loop, self._x_ref = PositionLoop(self.hold_gains), x_ref

    def _release_hold(self) -> None:
        self._loop = None
        self.device.set_command(0.0)

    def _write_command(self, u: float) -> None:
        self.device.set_command(u)

    def _pace(self, cycles: int = 1) -> None:
        if not self.realtime or self.real_clock:
            return
        now = time.monotonic()
        if self._t0_wall is None:
            self._t0_wall = now - self.device._t_s
        deadline = self._t0_wall + self.device._t_s
        if deadline > now:
            time.sleep(deadline - now)

    def _check_fault(self, fault_code: int) -> None:
        if fault_code:
            raise DriveFaultError(
                f"drive fault 0x{fault_code:04X}: {self.device.fault_reason}", fault_code
            )

    def _read_feedback(self) -> Feedback:
        s = self.device.sample()
        self._check_fault(s.fault_code)
        return Feedback(s.t_s, s.velocity, s.position, s.fault_code)

    def _exchange(self, u: float) -> Feedback:
        self._pace()
        if self._loop is not None:
            return self._held(u)
        s = self.device.exchange(u)
        self._check_fault(s.fault_code)
        return Feedback(s.t_s, s.velocity, s.position, s.fault_code)

    def _held(self, offset: float) -> Feedback:
        """One cycle of the drive's own loop: the loop acts on the feedback the host receives."""
        assert self._loop is not None
        s = self.device.sample()
        self._check_fault(s.fault_code)
        error = self._x_ref - s.position
        total = self._loop.torque(error, s.velocity, offset, self.limits.max_command, self.device.cycle_s)
        if not (math.isfinite(s.position) and math.isfinite(s.velocity)):
            total = 0.0
        self.device.exchange(total)
        fb = Feedback(s.t_s, s.velocity, s.position, s.fault_code, applied=self._applied)
        self._applied = self.device.command
        return fb

    def _exchange_block(self, u: np.ndarray) -> BlockFeedback:
        if self._loop is not None:
            rows = [self._held(float(uk)) for uk in u]
            applied = [r.applied for r in rows[1:]] + [self._applied]
            return BlockFeedback(
                t_s=np.array([r.t_s for r in rows]), velocity=np.array([r.velocity for r in rows]),
                position=np.array([r.position for r in rows]), applied=np.array(applied),
            )  # fmt: skip
        if self.realtime or self.device.frozen_feedback is not None:
            return super()._exchange_block(u)
        self._check_fault(self.device.fault_code)
        t, v, x = self.device.exchange_block(u)
        return BlockFeedback(t_s=t, velocity=v, position=x, applied=u.copy())

    def _fault_code(self) -> int:
        return self.device.fault_code

    def _reset_fault(self) -> None:
        self.device.reset_fault()

    def _info(self) -> DriveInfo:
        p = self.device.params
        return DriveInfo(
            transport="sim",
            vendor="servobench",
            product="simulated DC servo with friction",
            firmware="sim",
            state=self.device.state.value,
            fault_code=self.device.fault_code,
            units=dict(self.units),
            extra={"M": p.M, "B": p.B, "coulomb_pos": p.coulomb_pos, "coulomb_neg": p.coulomb_neg},
        )

    @property
    def power_state(self) -> PowerState:
        return self.device.state
