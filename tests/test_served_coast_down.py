"""A served drive coasts down in wall-clock time, and the next session finds it at rest (issue 13 §2).

Issue 13 quotes a served drive that, after a quick stop, still reported
v ≈ 0.45 while disabled, so the next run started moving. Here a host spins
the axis up, leaves (quick stop, disable, close), nobody polls for a while,
and a fresh session must find it at rest where the plant, simulated offline
with the same commands, comes to rest.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from servobench.bench.testing.served import ServedSim
from servobench.drivers.registry import open_drive
from servobench.sim_backend.physics.plant import PlantParams, simulate
from servobench.sim_backend.servers.serve import TRANSPORTS

PARAMS = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)
SIM = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"
CYCLE_S = 0.002
#: Resolution of what each transport reports: Modbus micro-units, the ODrive's "%f".
RESOLUTION = {"modbus-tcp": 1e-6, "modbus-rtu": 1e-6, "serial": 1e-6, "canopen": 1e-3}


@pytest.mark.parametrize("transport", sorted(TRANSPORTS))
def test_a_served_axis_coasts_down_while_nobody_polls(transport):
    u = np.full(100, 2.0)  # 0.2 s: v reaches about 1.3
    with ServedSim(transport, SIM, clock="lockstep") as served:
        url = served.url + ("&" if "?" in served.url else "?") + "pace=fast"
        with open_drive(url) as drive:
            drive.set_cycle(CYCLE_S)
            drive.enable()
            last = [drive.exchange(uk)[0] for uk in u][-1]
        assert last.velocity > 1.0  # it was moving when the host left (quick stop, disable)
        time.sleep(0.5)  # the coast takes ~0.13 s; nobody polls
        with open_drive(url) as fresh:
            first = fresh.read()
            time.sleep(0.2)
            second = fresh.read()
    # offline: the same commands, then none (exact zero-order hold), until at rest
    _, x_ref = simulate(np.concatenate([u, np.zeros(500)]), 1 / CYCLE_S, PARAMS)
    tol = RESOLUTION[transport]
    assert first.velocity == pytest.approx(0.0, abs=tol)
    assert first.position == pytest.approx(x_ref[-1], abs=max(tol, 1e-6))
    assert (second.velocity, second.position) == pytest.approx((first.velocity, first.position))


@pytest.mark.parametrize("transport", sorted(TRANSPORTS))
def test_each_session_starts_with_the_drive_clock_at_zero(transport):
    # Issue 10 §4: after an overrun the next run met "the drive clock stands at 6.031 s", then a
    # first time stamp of 120.8 s. A host that vanishes mid-run (no close) leaves nothing behind.
    with ServedSim(transport, SIM, clock="lockstep") as served:
        url = served.url + "&pace=fast&watchdog=0.3"
        gone = open_drive(url)
        gone.open()
        gone.set_cycle(CYCLE_S)
        gone.enable()
        for _ in range(150):
            gone.exchange(1.0)
        gone._close()  # the link drops; no stop, no disable: the drive's watchdog acts
        time.sleep(0.6)
        with open_drive(url) as fresh:
            fresh.reset_fault()  # the watchdog fault the vanished host left
            fresh.set_cycle(CYCLE_S)
            fresh.enable()
            t = np.array([fresh.exchange(0.0)[0].t_s for _ in range(20)])
    np.testing.assert_allclose(t, np.arange(20) * CYCLE_S, rtol=0, atol=2e-6)
