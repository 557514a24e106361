"""A served drive whose clock drifts against the host's (``drift=PPM``, ``serve-sim --drift``).

A real drive's crystal runs some 10-100 ppm off the host's: its time stamps
step by its own seconds and its ticks slide against the host's cycle. In
process, on a fake wall clock, every case is exact: the references are the
tick grid ``phase + k T / rate`` worked by hand, the stamps ``rate`` times
the wall time elapsed, and the first-order step response with the command
acting from the first (drifted) tick after its arrival. One case goes end
to end through ``serve-sim --drift`` over Modbus TCP in real time.
"""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest
from fake_clock import FakeClock

from servobench.bench.log.identity import axis_of_url
from servobench.bench.testing.served import PATIENT_KEYS, ServedSim
from servobench.drivers.registry import open_drive
from servobench.drivers.url import parse_drive_url
from servobench.errors import DriveConfigError
from servobench.sim_backend.device import REAL, SimulatedDevice, device_from_url
from servobench.sim_backend.drive_tick import TickGrid, draw_phase
from servobench.sim_backend.physics.plant import PlantParams

T = 1e-3
TAU_S = 0.01
#: Pole -100 rad/s, no friction: v(t) = u/B (1 - exp(-t B/M)) from rest.
LINEAR = PlantParams(M=0.01, B=1.0, coulomb_pos=0.0, coulomb_neg=0.0, seed=4)
EXACT = 1e-9


def drifting(drift_ppm: float, tick_s: float = T) -> tuple[SimulatedDevice, FakeClock]:
    clock = FakeClock()
    dev = SimulatedDevice(
        LINEAR, cycle_s=T, clock=clock, clock_mode=REAL, tick_s=tick_s, drift_ppm=drift_ppm
    )
    dev.begin_session()
    dev.enable()
    return dev, clock


def response(t_s: float, u: float = 1.0) -> float:
    return u * (1.0 - math.exp(-max(t_s, 0.0) / TAU_S))


@pytest.mark.parametrize("drift_ppm", [100.0, -250.0, 5000.0])
def test_the_ticks_fall_a_drifted_tick_apart_and_the_stamps_count_the_drives_own(drift_ppm):
    dev, clock = drifting(drift_ppm)
    rate = 1.0 + drift_ppm * 1e-6
    grid = dev.tick
    assert grid == TickGrid(T, draw_phase(T, LINEAR.seed), rate)
    assert grid.instant(7) - grid.instant(3) == pytest.approx(4 * T / rate, abs=1e-12)
    k0 = grid.index_at(100.0)  # the session began in this tick: the drive clock reads 0 there
    clock.now = grid.instant(k0 + 2) + 0.3 * T / rate
    dev.exchange(1.0)  # acts from tick k0 + 3
    for j in (k0 + 3, k0 + 40, k0 + 4000):
        clock.now = grid.instant(j) + 0.77 * T / rate  # inside tick j on the wall clock
        s = dev.sample()
        assert s.t_s == pytest.approx((j - k0) * T, abs=1e-12)  # whole ticks of the drive's clock
        assert s.velocity == pytest.approx(response((j - k0 - 3) * T / rate), abs=EXACT)
        assert dev.wall_instant_of(s.t_s) == pytest.approx(grid.instant(j), abs=1e-9)
    # over 4000 ticks the drive's grid slid 4000 T (rate - 1) / rate against a grid of the host's rate
    slide = (grid.instant(k0 + 4000) - grid.instant(k0)) - 4000 * T
    assert slide == pytest.approx(-4000 * T * (rate - 1) / rate, rel=1e-9)


def test_the_record_gives_its_delays_in_the_hosts_seconds():
    dev, clock = drifting(1000.0)
    grid = dev.tick
    for k in range(5, 25):
        clock.now = grid.instant(grid.index_at(100.0) + 2 * k) + 0.5 * grid.period_s
        dev.exchange(1.0 if k % 2 else -1.0)
    record = dev.timing()
    assert record["drift_ppm"] == pytest.approx(1000.0, abs=1e-9)
    assert record["mean_delay_s"] == pytest.approx(T / 1.001, abs=1e-12)


def test_without_a_tick_the_stamps_run_at_the_drives_rate():
    dev, clock = drifting(-80.0, tick_s=0.0)
    assert dev.tick is None
    for wall in (0.0123, 1.5, 30.0):
        clock.now = 100.0 + wall
        s = dev.exchange(0.5)
        assert s.t_s == pytest.approx(wall * (1 - 80e-6), abs=1e-12)
        assert dev.wall_instant_of(s.t_s) == pytest.approx(100.0 + wall, abs=1e-9)


def test_no_drift_gives_the_grid_and_stamps_of_before():
    a, b = drifting(0.0), SimulatedDevice(LINEAR, cycle_s=T, clock=FakeClock(), clock_mode=REAL, tick_s=T)
    assert a[0].tick == b.tick and a[0].clock_rate == 1.0


# ------------------------------------------------------------------ configuration
def test_a_drift_needs_the_real_clock_and_a_sane_value():
    with pytest.raises(DriveConfigError, match="needs clock=real"):
        device_from_url("sim://?M=0.01&B=1&drift=50")
    with pytest.raises(DriveConfigError, match="needs clock=real"):
        open_drive("sim://?M=0.01&B=1&drift=50")
    for bad in ("nan", "x", "20000", "-1e5"):
        with pytest.raises(DriveConfigError, match="drift"):
            device_from_url(f"sim://?M=0.01&B=1&clock=real&drift={bad}")
    keyword_wins = device_from_url("sim://?M=0.01&B=1&clock=real&drift=30", drift_ppm=-20.0)
    assert keyword_wins.clock_rate == 1.0 - 20e-6
    assert device_from_url("sim://?M=0.01&B=1&clock=real&drift=30").clock_rate == 1.0 + 30e-6


def test_the_drift_is_the_drives_not_the_plants():
    assert axis_of_url(parse_drive_url("sim://?M=0.1&B=1&tick=0.001&drift=40")) == "sim://?B=1&M=0.1"


# ------------------------------------------------------------------ end to end
def test_a_served_modbus_drive_stamps_by_its_own_drifting_clock(tmp_path):
    """``serve-sim --tick 0.001 --drift 2000`` (winning over the URL's drift=5): ~600 FC23 at
    ~1 kHz; the stamps run 2000 ppm fast against the host's clock, on one grid of ticks."""
    state = tmp_path / "state.json"
    plant = "sim://?M=0.01&B=1&fc_pos=0&fc_neg=0&drift=5"
    args = ["--tick", "0.001", "--drift", "2000", "--state-file", str(state)]
    with ServedSim("modbus-tcp", plant, args, clock="real") as sim:
        stamps, hosts, widths = [], [], []
        with open_drive(sim.url + PATIENT_KEYS["modbus-tcp"]) as drive:
            drive.enable()
            deadline = time.monotonic()
            for k in range(600):
                before = time.monotonic()
                stamps.append(drive.exchange(0.2 if k % 2 else -0.2)[0].t_s)
                after = time.monotonic()
                hosts.append(0.5 * (before + after))
                widths.append(after - before)
                deadline += 1e-3
                time.sleep(max(0.0, deadline - time.monotonic()))
            drive.disable()
    assert sim.returncode == 0, sim.stderr
    steps = [(b - a) / T for a, b in zip(stamps, stamps[1:], strict=False)]
    assert all(abs(s - round(s)) * T <= 1e-6 + 1e-9 for s in steps), steps  # whole drive ticks
    # the drive's seconds per host second: a line through the exchanges that took under 0.5 ms
    # (each stamp is up to a tick before its bracket's middle: a slope error of about 70 ppm
    # over 0.6 s, against the 2000 ppm looked for and the 0 of a drive on the host's clock)
    quick = np.asarray(widths) < 0.5e-3
    assert np.count_nonzero(quick) > 200
    rate = np.polyfit(np.asarray(hosts)[quick], np.asarray(stamps)[quick], 1)[0]
    assert rate - 1.0 == pytest.approx(2000e-6, abs=700e-6)
    record = json.loads(state.read_text())["tick"]
    assert record["drift_ppm"] == pytest.approx(2000.0, abs=1e-6)
    assert record["mean_delay_s"] == pytest.approx(T / 1.002, abs=1e-6)
