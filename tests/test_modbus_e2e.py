"""Modbus TCP and RTU end to end: ``servobench serve-sim`` in a child process, the real client.

The served drive is lock-step (one FC23 = one cycle), so a square wave streamed
over the wire must reproduce :func:`servobench.sim_backend.physics.plant.simulate` of the same
command to the register resolution (1e-6 units).
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from servobench.bench.testing.served import ServedSim
from servobench.drivers.registry import open_drive
from servobench.errors import DriveFaultError
from servobench.sim_backend.device import WATCHDOG_FAULT
from servobench.sim_backend.physics.plant import PlantParams, simulate

SIM_URL = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"
PARAMS = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)
#: Cycles per transport: RTU at 115200 baud runs ~120 cycles/s.
CYCLES = {"modbus-tcp": 400, "modbus-rtu": 240}
RESOLUTION = 1e-6  # velocity and position LSB of the servobench-sim map


def square_wave(n: int, half_period: int = 60, amplitude: float = 1.0) -> np.ndarray:
    return np.where((np.arange(n) // half_period) % 2 == 0, amplitude, -amplitude)


@pytest.mark.parametrize("transport", ["modbus-tcp", "modbus-rtu"])
def test_square_wave_matches_the_plant(transport):
    u = square_wave(CYCLES[transport])
    with ServedSim(transport, SIM_URL, clock="lockstep") as served:
        assert served.url.startswith(transport.replace("-", "+") + "://")
        with open_drive(served.url) as drive:
            drive.set_cycle(0.001)
            drive.enable()
            rows = [drive.exchange(float(uk))[0] for uk in u]
            info = drive.info()
        assert served.stop() == 0  # SIGINT: server, pty link and sockets shut down cleanly
    v_ref, x_ref = simulate(u, 1000.0, PARAMS)
    v = np.array([r.velocity for r in rows])
    x = np.array([r.position for r in rows])
    t = np.array([r.t_s for r in rows])
    assert v.max() > 0.15 and v.min() < -0.15  # it moved, both ways
    np.testing.assert_allclose(v, v_ref, rtol=0, atol=RESOLUTION)
    np.testing.assert_allclose(x, x_ref, rtol=0, atol=RESOLUTION)
    np.testing.assert_allclose(t, np.arange(u.size) * 1e-3, rtol=0, atol=1e-6)  # the drive's clock
    assert (info.vendor, info.state, info.fault_code) == ("servobench", "enabled", 0)


HOST = """
import sys
from servobench.drivers.registry import open_drive
drive = open_drive(sys.argv[1])
drive.open()
drive.set_cycle(0.001)
drive.enable()
k = 0
while True:
    drive.exchange(0.8 if (k // 50) % 2 == 0 else -0.8)
    k += 1
    if k == 60:
        print("streaming", flush=True)
"""


@pytest.mark.parametrize("transport", ["modbus-tcp", "modbus-rtu"])
def test_killed_host_trips_the_drive_watchdog(transport):
    watchdog_s = 0.2
    with ServedSim(transport, SIM_URL, clock="lockstep") as served:
        host = subprocess.Popen(
            [sys.executable, "-c", HOST, f"{served.url}&watchdog={watchdog_s}"],
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            assert host.stdout.readline().strip() == "streaming"
        finally:
            host.send_signal(signal.SIGKILL)
            host.wait(5)
            host.stdout.close()
        time.sleep(watchdog_s + 0.3)
        with open_drive(served.url) as fresh:  # a fresh client on the same link
            assert fresh.fault_code() == WATCHDOG_FAULT
            assert fresh.info().state == "fault"
            with pytest.raises(DriveFaultError) as err:
                fresh.exchange(0.0)
            assert err.value.code == WATCHDOG_FAULT
            with pytest.raises(DriveFaultError):
                fresh.enable()
            fresh.reset_fault()
            assert fresh.fault_code() == 0
            fresh.enable()
            assert fresh.info().state == "enabled"
