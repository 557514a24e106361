"""A served drive runs in wall-clock time and starts each host session clean (issues 10 §4, 13 §2).

The device runs on a fake wall clock here, so every case is exact and
instant; the reference is the plant simulated offline with the same command
(exact zero-order hold), or the Coulomb coast-down solved by hand.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from fake_clock import FakeClock

from servobench.sim_backend.device import WATCHDOG_FAULT, PowerState, SimulatedDevice
from servobench.sim_backend.physics.plant import PlantParams, simulate

PARAMS = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)
DT = 1e-3


def coast_to_rest(v0: float, p: PlantParams = PARAMS) -> tuple[float, float]:
    """Time [s] and distance of a coast from v0 > 0 to rest: M dv/dt = -B v - Fc, solved by hand."""
    tau, v_inf = p.M / p.B, -p.coulomb_pos / p.B
    t_stop = tau * math.log((v0 - v_inf) / (0 - v_inf))
    distance = v_inf * t_stop + (v0 - v_inf) * tau * (1 - math.exp(-t_stop / tau))
    return t_stop, distance


def streamed(clock: FakeClock, wall_clock: bool = True, n: int = 200, u: float = 2.0):
    device = SimulatedDevice(PARAMS, cycle_s=DT, clock=clock, wall_clock=wall_clock)
    device.enable()
    for _ in range(n):
        clock.now += DT
        device.exchange(u)
    return device


def test_lock_step_while_enabled_whatever_the_host_delays():
    clock = FakeClock()
    device = SimulatedDevice(PARAMS, cycle_s=DT, clock=clock, wall_clock=True)
    device.enable()
    u = np.where(np.arange(300) < 150, 2.0, -2.0)
    v = []
    for k, uk in enumerate(u):
        clock.now += DT if k % 50 else 1.0  # the host stalls now and then
        v.append(device.exchange(uk).velocity)
    np.testing.assert_allclose(v, simulate(u, 1 / DT, PARAMS)[0], rtol=0, atol=1e-12)
    assert device.idle_s == 0.0


def test_quick_stop_then_the_axis_coasts_down_in_wall_clock_time():
    clock = FakeClock()
    device = streamed(clock)
    v0, x0 = device.plant.state.v, device.plant.state.x  # the state the last cycle reached
    t_stop, distance = coast_to_rest(v0)
    device.quick_stop()
    device.disable()
    clock.now += 0.5 * t_stop  # a look half-way: still coasting, as the hand solution says
    half = device.sample()
    assert half.state is PowerState.DISABLED and 0 < half.velocity < v0
    clock.now += 2.0  # nobody polls for 2 s
    rest = device.sample()
    assert rest.velocity == 0.0
    assert rest.position == pytest.approx(x0 + distance, rel=1e-9)
    assert device.idle_s == pytest.approx(0.5 * t_stop + 2.0 - DT, rel=1e-9)  # the last cycle ran ahead
    assert rest.t_s == half.t_s  # the drive clock counts clocked cycles: nobody clocked it


def test_the_in_process_drive_stays_lock_step():
    clock = FakeClock()
    device = streamed(clock, wall_clock=False)
    v0 = device.plant.state.v
    device.quick_stop()
    clock.now += 5.0
    assert device.sample().velocity == pytest.approx(v0)  # nothing moves until it is clocked


def test_a_watchdog_trip_is_integrated_up_to_its_moment():
    clock = FakeClock()
    device = streamed(clock, n=20, u=0.0)  # at rest at the origin: below breakaway
    device.set_watchdog(0.1)
    device.exchange(1.5)  # the host's last command, then silence
    clock.now += 0.3
    assert device.check_watchdog() and device.fault_code == WATCHDOG_FAULT
    clock.now += 2.0
    rest = device.sample()
    # 1.5 acted for the watchdog's 0.1 s after the host fell silent, then the axis coasted
    _, x_ref = simulate(np.concatenate([np.full(100, 1.5), np.zeros(2400)]), 1 / DT, PARAMS)
    assert rest.velocity == 0.0
    assert rest.position == pytest.approx(x_ref[-1], rel=1e-9)


def test_begin_session_starts_clean_and_keeps_the_axis_where_it_is():
    clock = FakeClock()
    device = streamed(clock, n=500)
    device.set_watchdog(0.2)
    assert device.sample().t_s == pytest.approx(0.5)
    device.begin_session()  # a new host: still enabled and spinning
    s = device.sample()
    assert (s.t_s, s.state, device.command) == (0.0, PowerState.DISABLED, 0.0)
    assert device.watchdog_s == 0.2 and device.sessions == 1  # settings kept
    x = s.position
    clock.now += 2.0
    device.begin_session()
    assert device.sample().velocity == 0.0 and device.sample().position > x  # it coasted


def test_a_latched_fault_survives_a_new_session():
    clock = FakeClock()
    device = streamed(clock, n=10)
    device.fault(0x2310, "test")
    device.begin_session()
    assert device.state is PowerState.FAULT and device.fault_code == 0x2310


def test_set_cycle_rebases_the_clock_instead_of_jumping():
    clock = FakeClock()
    device = streamed(clock, n=1000)  # 1 s at 1 ms
    device.set_cycle(0.01)
    clock.now += 0.01
    t = device.exchange(0.0).t_s
    assert t == pytest.approx(1.0)  # not 1000 cycles * 10 ms
    clock.now += 0.01
    assert device.exchange(0.0).t_s == pytest.approx(1.01)


def test_polls_while_disabled_see_the_plant_in_wall_clock_time():
    clock = FakeClock()
    device = streamed(clock, n=200)
    device.disable()
    v0, x0 = device.plant.state.v, device.plant.state.x
    t0 = device.sample().t_s
    for _ in range(10):
        clock.now += 0.005  # a host reading the state every 5 ms
        device.step()
    # the clock counts the cycles it was clocked ...
    assert device.sample().t_s == pytest.approx(t0 + 10 * DT)
    # ... the plant coasted the 50 ms of wall time: M dv/dt = -B v - Fc, solved by hand
    tau, v_inf, t = PARAMS.M / PARAMS.B, -PARAMS.coulomb_pos / PARAMS.B, 0.05
    assert t < coast_to_rest(v0)[0]
    v_hand = v_inf + (v0 - v_inf) * math.exp(-t / tau)
    x_hand = x0 + v_inf * t + (v0 - v_inf) * tau * (1 - math.exp(-t / tau))
    assert device.plant.state.v == pytest.approx(v_hand, rel=1e-9)
    assert device.plant.state.x == pytest.approx(x_hand, rel=1e-9)
