"""The EtherCAT master's keep-alive never undoes the host's own frame.

While the axis is not enabled, a keep-alive thread re-sends the last outputs
whenever the host has been silent for ``KEEPALIVE_S``, so the slave's SM
watchdog does not trip. It read those outputs before it took the link's lock:
when the host sent a new frame in between (the controlword of an enable), the
keep-alive sent the older outputs after it. A served slave then went from
OPERATION ENABLED straight to SWITCH ON DISABLED (statusword 0x0260: the
controlword 0 of before, "disable voltage"), which two fresh-clone suites
showed as ``sidbe`` stopping at the start of its hold trial. Here a recording
stand-in for SOEM holds the frames in order: the last frame must carry the
host's newest outputs.
"""

from __future__ import annotations

import time

from servobench.drivers.ethercat.master import KEEPALIVE_S, EthercatMaster
from servobench.drivers.ethercat.options import EthercatOptions
from servobench.drivers.url import parse_drive_url


class RecordingSoem:
    """SOEM's master and slave in one: records the outputs of every frame, answers each."""

    expected_wkc = 3
    dc_time = 0

    def __init__(self) -> None:
        self.output = b""
        self.input = b"\x00\x00"
        self.sent: list[bytes] = []

    def send_processdata(self) -> None:
        self.sent.append(bytes(self.output))

    def receive_processdata(self, timeout_us: int, release_gil: bool = True) -> int:
        return self.expected_wkc


def test_the_keep_alive_resends_the_newest_outputs_never_older_ones():
    bus = EthercatMaster(EthercatOptions.from_url(parse_drive_url("ethercat://eth9?slave=1")))
    soem = RecordingSoem()
    bus.master = bus.slave = soem
    old, new = b"\x00\x00", b"\x0f\x00"  # controlword 0, then 15 (enable operation)
    bus.outputs = old
    bus.keep_alive = True  # the axis is not enabled yet: the keep-alive may send
    bus._last_cycle = 0.0  # the host has been silent long
    with bus._lock:  # the host is sending its frame while the keep-alive wakes up
        bus.start_keepalive()
        time.sleep(5 * KEEPALIVE_S)  # the keep-alive is waiting for the link now
        # the host's frame, as cycle() sends it under the lock
        bus.outputs = soem.output = new
        soem.send_processdata()
        bus._last_cycle = 0.0  # and silent again at once: the keep-alive still has to send
    deadline = time.monotonic() + 2.0
    while len(soem.sent) < 2 and time.monotonic() < deadline:
        time.sleep(KEEPALIVE_S)
    bus.stop_keepalive()
    assert bus.keepalive_error is None
    assert soem.sent[0] == new and len(soem.sent) >= 2, soem.sent
    assert all(frame == new for frame in soem.sent), soem.sent  # nothing older after it
