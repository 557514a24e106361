"""The torque that acted, read back with the next sample (issue 28): late commands made visible.

A CiA 402 drive maps torque actual 0x6077 in its TxPDO; on EtherCAT and
CANopen the runner takes it as the drive's word on what acted over each
cycle. A frame or RPDO that misses its SYNC leaves the command before in
force one cycle longer: the log must say so and carry the command that
acted. The stand-in drive here misses chosen cycles on purpose and reports,
as 0x6077 does, the command in force over the cycle before each sample.
"""

from __future__ import annotations

import numpy as np

from servobench.bench.log.io import read_log
from servobench.bench.run.runner import stream_runs
from servobench.drivers.base import Feedback
from servobench.drivers.sim import SimDrive

PLANT = "M=0.01&B=1&fc_pos=0.5&fc_neg=0.4"
LATE = {40, 50, 75, 76, 150}  # 50, 75 and 150 fall on a change of command, 76 just after one


class LateFramesDrive(SimDrive):
    """Leaves the command before in force at the cycles in :data:`LATE` (their frames came after
    the SYNC) and reads back, with each sample, the command that acted over the cycle before it."""

    def __init__(self, url: str) -> None:
        super().__init__(url)
        self.cycle = 0
        self.acting = 0.0
        self.acted: list[float] = []

    def _exchange(self, u: float) -> Feedback:
        before = self.acting
        if self.cycle not in LATE:
            self.acting = u
        self.acted.append(self.acting)
        self.cycle += 1
        s = self.device.exchange(self.acting)
        return Feedback(s.t_s, s.velocity, s.position, applied=before)


def test_late_commands_are_logged_as_they_acted_and_counted(tmp_path):
    u = np.repeat(np.array([1.5, -1.0, 2.0, -2.0, 0.5, -1.5, 1.0, -0.5]), 25)  # 200 cycles
    with LateFramesDrive(f"sim://?clock=real&{PLANT}") as drive:
        stream_runs(drive, [(1, u)], 500.0, tmp_path / "log.csv")
        acted = np.array(drive.acted)
    log = read_log(tmp_path / "log.csv")
    logged = log.runs[0].u
    assert np.array_equal(logged[:-1], acted[:-1])  # the last row has no cycle after it to tell
    # a late frame that repeats the command in force changes nothing (40); 76 is late again
    assert int(log.metadata["late_commands"]) == 4
    assert "0x6077" in log.metadata["u_read_back"]
    assert not np.array_equal(logged, u)


def test_a_drive_without_read_back_logs_the_commands_sent(tmp_path):
    u = np.repeat(np.array([1.5, -1.0]), 50)
    with SimDrive(f"sim://?clock=real&{PLANT}") as drive:
        stream_runs(drive, [(1, u)], 500.0, tmp_path / "log.csv")
    log = read_log(tmp_path / "log.csv")
    assert np.array_equal(log.runs[0].u, u)
    assert "late_commands" not in log.metadata and "u_read_back" not in log.metadata
