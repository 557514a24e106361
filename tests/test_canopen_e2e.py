"""CANopen end to end across processes: ``servobench serve-sim --transport canopen``.

The served drive runs in its own process with its socketcand hub; the host
side opens the announced URL through the registry, as a user would.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Iterator

import numpy as np
import pytest

from servobench.bench.testing.served import ServedSim
from servobench.drivers.registry import open_drive
from servobench.drivers.url import parse_drive_url
from servobench.sim_backend.physics.plant import PlantParams, simulate

SIM = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"
PARAMS = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)
#: A host that enables, streams and keeps streaming until it is killed.
STREAMING_HOST = """
import sys
from servobench.drivers.registry import open_drive
from servobench.drivers.url import parse_drive_url
drive = open_drive(sys.argv[1]).open()
drive.set_cycle(0.001)
drive.enable()
for _ in range(200):
    drive.exchange(0.8)
print("streaming", flush=True)
while True:
    drive.exchange(0.8)
"""


@pytest.fixture(scope="module")
def served() -> Iterator[ServedSim]:
    with ServedSim("canopen", SIM, clock="lockstep") as sim:
        yield sim
    assert sim.returncode == 0, sim.stderr


def test_announced_url(served: ServedSim) -> None:
    assert served.url.startswith("canopen://vcan0?interface=socketcand&host=127.0.0.1&port=")
    query = parse_drive_url(served.url).query
    assert query["node"] == "2"
    assert not {"pos_scale", "vel_scale"} & set(query)  # the drive's factor group tells the units


def test_square_wave_matches_the_plant(served: ServedSim) -> None:
    n = 400
    u = np.where((np.arange(n) // 50) % 2 == 0, 1.0, -1.0)
    with open_drive(served.url) as drive:
        drive.set_cycle(0.001)
        drive.enable()
        t0 = time.perf_counter()
        rows = [drive.exchange(uk)[0] for uk in u]
        rate_hz = n / (time.perf_counter() - t0)
        drive.disable()
    v_ref, x_ref = simulate(u, 1000.0, PARAMS)
    np.testing.assert_allclose([r.velocity for r in rows], v_ref, atol=1e-6)
    np.testing.assert_allclose([r.position for r in rows], x_ref, atol=1e-6)
    t = np.array([r.t_s for r in rows])
    np.testing.assert_allclose(np.diff(t), 1e-3, atol=1e-9)  # the drive's clock, one cycle per SYNC
    assert rate_hz > 200, f"{rate_hz:.0f} exchanges/s: the link is far slower than it should be"


def test_killed_host_trips_the_drive_watchdog(served: ServedSim) -> None:
    host = subprocess.Popen(
        [sys.executable, "-c", STREAMING_HOST, served.url + "&watchdog=0.2"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        line = host.stdout.readline()
        assert line.strip() == "streaming", host.stderr.read() if host.poll() is not None else line
        host.send_signal(signal.SIGKILL)
        host.wait(5)
    finally:
        if host.poll() is None:
            host.kill()
        host.stdout.close()
        host.stderr.close()
    time.sleep(0.5)  # consumer time 0.2 s, plus margin
    with open_drive(served.url) as drive:
        info = drive.info()
        assert info.state == "FAULT"
        assert info.fault_code == 0x8130
        assert drive.fault_code() == 0x8130
        # the torque is off: after a fault reset the axis coasts to rest with zero command
        drive.reset_fault()
        assert drive.info().state == "SWITCH ON DISABLED"
        drive.enable()
        rows = [drive.exchange(0.0)[0] for _ in range(300)]
        # it was moving when the host died; served drives coast down in wall-clock time
        # (issue 13 §2), so with its torque off it has come to rest by now, where it coasted to
        assert rows[0].position > 0.0
        assert rows[0].velocity == 0.0 and rows[-1].velocity == 0.0
