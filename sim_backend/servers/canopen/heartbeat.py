"""The served CiA 402 drive's heartbeat consumer (0x1016) and abort connection option (0x6007).

Host heartbeats (COB-ID 0x700 + the host's node id in 0x1016) feed the
device watchdog, and nothing else does (CiA 301 7.2.8.3.2.4): a host whose
heartbeat stops while its PDOs, SYNCs and SDOs go on is detected. The
watchdog runs with the consumer time when 0x6007 is 1 (fault on connection
loss), which is also what the served drive does when its object dictionary
has no 0x6007; with 0x6007 = 0 it does not run. The tripping itself is the
sim_backend watchdog thread's (fault 0x8130).
"""

from __future__ import annotations

import time

import canopen

from servobench.sim_backend.device import SimulatedDevice


class HeartbeatConsumer:
    """0x1016 sub-index 1 and 0x6007 of one served node."""

    def __init__(self, device: SimulatedDevice) -> None:
        self.device = device
        device.activity_feeds_watchdog = False  # only the heartbeat counts
        self.network: canopen.Network | None = None
        self.abort_option = 1  #: 0x6007: 0 no action, 1 fault
        self._cob: int | None = None
        self._time_s: float | None = None
        self._last_heartbeat = -float("inf")  #: time.monotonic() of the host's last heartbeat

    def configure(self, value: int) -> None:
        """A 0x1016:1 entry: bits 22..16 the producer's node id, bits 15..0 the time [ms]."""
        node_id, time_ms = (value >> 16) & 0x7F, value & 0xFFFF
        if self.network is not None and self._cob is not None:
            self.network.unsubscribe(self._cob, self.on_heartbeat)
            self._cob = None
        if node_id and time_ms:
            self._cob = 0x700 + node_id
            self._time_s = time_ms / 1000.0
            self._last_heartbeat = time.monotonic()  # the host writing it is present
            if self.network is not None:
                self.network.subscribe(self._cob, self.on_heartbeat)
        else:
            self._time_s = None
        self.apply()

    def set_abort_option(self, option: int) -> None:
        self.abort_option = option
        self.apply()

    def apply(self) -> None:
        self.device.set_watchdog(self._time_s if self.abort_option == 1 else None)
        self.device.feed_life_signal()  # the host configuring it is present

    def on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self._last_heartbeat = time.monotonic()
        self.device.feed_life_signal()

    def host_present(self) -> bool:
        """True while a host consumed in 0x1016 heartbeats within the consumer time.

        A host that closed cleanly wrote 0x1016:1 = 0; one that vanished fell
        silent: either way the next host's NMT command begins a new session.
        """
        return self._time_s is not None and time.monotonic() - self._last_heartbeat <= self._time_s
