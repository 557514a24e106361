"""``sim://`` -- the simulated DC servo with friction, in-process.

``sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4&noise=0.001&pace=fast`` (see
:mod:`servobench.sim_backend.simurl` for every key). ``pace=real`` paces each cycle to
wall-clock time like a real drive; ``pace=fast`` (default) runs as fast as
the host asks, and supports block exchange for batch work.
Timestamps are the drive's own clock (cycle count times cycle period).
"""

from __future__ import annotations

import time

import numpy as np

from servobench.drivers.base import BlockFeedback, Drive, DriveInfo, Feedback
from servobench.errors import DriveConfigError, DriveFaultError
from servobench.sim_backend.device import PowerState, SimulatedDevice
from servobench.sim_backend.simurl import plant_from_url, sim_query_keys, units_from_url


class SimDrive(Drive):
    """The simulated drive of :mod:`sim_backend`, driven in-process."""

    query_keys = sim_query_keys()
    drive_clock = True

    def __init__(self, url) -> None:
        super().__init__(url)
        pace = self.url.get_str("pace", "fast")
        if pace not in ("fast", "real"):
            raise DriveConfigError(f"sim pace must be 'fast' or 'real', got {pace!r}")
        self.realtime = pace == "real"
        self.supports_block = not self.realtime
        self.device = SimulatedDevice(plant_from_url(self.url))
        signal_units = units_from_url(self.url)
        self.units = {"u": signal_units.u, "v": signal_units.v, "x": signal_units.x}
        self._t0_wall: float | None = None

    def _open(self) -> None:
        self._t0_wall = None

    def _close(self) -> None:
        self.device.disable()

    def _configure_watchdog(self, timeout_s: float) -> None:
        self.device.set_watchdog(timeout_s)

    def _set_cycle(self, period_s: float) -> None:
        self.device.set_cycle(period_s)

    def _enable(self) -> None:
        self.device.enable()

    def _disable(self) -> None:
        self.device.disable()

    def _quick_stop(self) -> None:
        self.device.quick_stop()

    def _write_command(self, u: float) -> None:
        self.device.set_command(u)

    def _pace(self, cycles: int = 1) -> None:
        if not self.realtime:
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
        s = self.device.exchange(u)
        self._check_fault(s.fault_code)
        return Feedback(s.t_s, s.velocity, s.position, s.fault_code)

    def _exchange_block(self, u: np.ndarray) -> BlockFeedback:
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
