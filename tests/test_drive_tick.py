"""A served drive with a control tick of its own (issue 28, part 1).

In process, on a fake wall clock, so every case is exact: a drive with a
tick ``T`` samples its plant only at its ticks ``phase + k T`` and a command
takes force at the first tick after its arrival. References: the
first-order step response solved by hand (a plant without friction, pole
-100 rad/s) with the command switching at that tick; the numbers the drive
gave before it had a tick (``tick=0`` must give them bit for bit). One case
goes end to end: ``serve-sim --tick`` over Modbus TCP at real time, its
time stamps on one grid of ticks and its state file's record of one tick of
action delay per FC23.
"""

from __future__ import annotations

import json
import math
import time

import pytest
from fake_clock import FakeClock

from servobench.bench.cli import main as cli_main
from servobench.bench.log.identity import axis_of_url
from servobench.bench.testing.served import PATIENT_KEYS, ServedSim
from servobench.drivers.registry import open_drive
from servobench.drivers.url import parse_drive_url
from servobench.errors import DriveConfigError
from servobench.sim_backend.device import REAL, PowerState, SimulatedDevice, device_from_url
from servobench.sim_backend.drive_tick import TickGrid, draw_phase
from servobench.sim_backend.physics.plant import PlantParams
from servobench.sim_backend.servers.ethercat.al import AlState

A_OP = AlState.OP

T = 1e-3
TAU_S = 0.01
#: Pole -100 rad/s, no friction: v(t) = u/B (1 - exp(-t B/M)) from rest.
LINEAR = PlantParams(M=0.01, B=1.0, coulomb_pos=0.0, coulomb_neg=0.0, seed=4)
NOISY = PlantParams(
    M=0.01, B=1.0, coulomb_pos=0.0, coulomb_neg=0.0, noise=0.01, noise_x=0.001, seed=4
)
#: A fake wall clock's instants carry rounding of about 1e-14 s at 100 s; a command misplaced by
#: one microsecond would show as 1e-4 [rad/s].
EXACT = 1e-9


def ticked(
    params: PlantParams = LINEAR, tick_s: float = T
) -> tuple[SimulatedDevice, FakeClock, TickGrid]:
    """An enabled drive with a tick on a fake clock, a new session begun at the clock's start."""
    clock = FakeClock()
    dev = SimulatedDevice(params, cycle_s=T, clock=clock, clock_mode=REAL, tick_s=tick_s)
    dev.begin_session()
    dev.enable()
    assert dev.tick is not None
    return dev, clock, dev.tick


def response(t_s: float, u: float = 1.0, v0: float = 0.0) -> float:
    """The velocity ``t_s`` after ``u`` took force at ``v0``: exact first order."""
    return u + (v0 - u) * math.exp(-max(t_s, 0.0) / TAU_S)


def at(clock: FakeClock, grid: TickGrid, k: int, fraction: float = 0.0) -> None:
    clock.now = grid.instant(k) + fraction * grid.tick_s


# ------------------------------------------------------------------ the tick grid
def test_the_phase_is_drawn_in_one_tick_seeded_by_the_plant():
    phases = [draw_phase(T, seed) for seed in range(200)]
    assert all(0.0 <= p < T for p in phases)
    assert min(phases) < 0.1 * T and max(phases) > 0.9 * T  # drawn over the whole tick
    assert draw_phase(T, 7) == draw_phase(T, 7) != draw_phase(T, 8)
    assert all(0.0 <= draw_phase(T, None) < T for _ in range(20))  # unseeded: random
    dev, _, grid = ticked()
    assert grid == TickGrid(T, draw_phase(T, LINEAR.seed))
    assert dev.timing()["phase_s"] == grid.phase_s


def test_a_command_acts_from_the_next_tick_and_is_held():
    dev, clock, grid = ticked()
    k = grid.index_at(clock.now) + 3
    at(clock, grid, k, 0.37)
    first = dev.exchange(1.0)
    assert first.velocity == 0.0
    # read mid-tick: the state of tick j, the command acting since tick k+1
    for j in range(k + 1, k + 12):
        at(clock, grid, j, 0.61)
        assert dev.sample().velocity == pytest.approx(response((j - k - 1) * T), abs=EXACT)
    at(clock, grid, k + 12, 0.05)
    dev.set_command(-1.0)  # acts from k+13: tick k+13 still shows the +1 response
    v13 = response(12 * T)
    for j in range(k + 12, k + 20):
        at(clock, grid, j, 0.5)
        up, down = response((j - k - 1) * T), response((j - k - 13) * T, -1.0, v13)
        assert dev.sample().velocity == pytest.approx(up if j <= k + 13 else down, abs=EXACT)


def test_a_command_on_a_tick_acts_from_the_next_and_a_read_on_a_tick_sees_it():
    dev, clock, grid = ticked()
    k = grid.index_at(clock.now) + 2
    at(clock, grid, k)
    s = dev.exchange(1.0)
    assert s.t_s == pytest.approx((k - grid.index_at(100.0)) * T, abs=1e-12)
    at(clock, grid, k + 1)
    assert dev.sample().velocity == 0.0  # the command takes force at this very tick
    at(clock, grid, k + 2)
    assert dev.sample().velocity == pytest.approx(response(T), abs=EXACT)


def test_a_read_returns_the_last_ticks_state_and_stamp():
    dev, clock, grid = ticked()
    k0 = grid.index_at(100.0)  # the session began in this tick: the drive clock reads 0 there
    dev.exchange(1.0)
    for j in range(k0 + 1, k0 + 30):
        at(clock, grid, j, (j * 0.618) % 1.0)  # anywhere inside tick j
        s = dev.sample()
        # the tick's instant on the drive clock
        assert s.t_s == pytest.approx((j - k0) * T, abs=1e-12)
        assert s.velocity == pytest.approx(response((j - k0 - 1) * T), abs=EXACT)
        assert dev.wall_instant_of(s.t_s) == pytest.approx(grid.instant(j), abs=1e-9)


def test_two_reads_in_one_tick_return_the_identical_sample():
    dev, clock, grid = ticked(NOISY)
    k = grid.index_at(clock.now) + 2
    at(clock, grid, k, 0.1)
    dev.exchange(1.0)
    at(clock, grid, k + 3, 0.05)
    a = dev.step()
    at(clock, grid, k + 3, 0.5)
    b = dev.sample()
    at(clock, grid, k + 3, 0.95)
    c = dev.exchange(1.0)
    assert a == b == c  # the same noise draw, the same stamp
    at(clock, grid, k + 4, 0.05)
    d = dev.sample()
    assert d.t_s == pytest.approx(a.t_s + T, abs=1e-12) and d.velocity != a.velocity


def test_of_two_commands_in_one_tick_the_later_wins():
    dev, clock, grid = ticked()
    k = grid.index_at(clock.now) + 2
    at(clock, grid, k, 0.2)
    dev.set_command(5.0)  # never acts
    at(clock, grid, k, 0.7)
    dev.set_command(1.0)
    for j in range(k + 1, k + 8):
        at(clock, grid, j, 0.3)
        assert dev.sample().velocity == pytest.approx(response((j - k - 1) * T), abs=EXACT)


def test_the_plants_transport_delay_adds_on_top_of_the_tick():
    clock = FakeClock()
    url = "sim://?M=0.01&B=1&fc_pos=0&fc_neg=0&seed=4&delay=0.0025&clock=real&tick=0.001"
    dev = device_from_url(url, clock=clock, cycle_s=T)
    grid = dev.tick
    dev.begin_session()
    dev.enable()
    k = grid.index_at(clock.now) + 2
    at(clock, grid, k, 0.4)
    dev.exchange(1.0)
    for j in range(k + 1, k + 10):
        at(clock, grid, j, 0.5)
        assert dev.sample().velocity == pytest.approx(response((j - k - 1) * T - 0.0025), abs=EXACT)


def test_the_power_stage_still_cuts_at_the_instant():
    dev, clock, grid = ticked()
    k = grid.index_at(clock.now) + 2
    at(clock, grid, k, 0.5)
    dev.exchange(1.0)
    at(clock, grid, k + 4, 0.25)
    v_cut = response(3.25 * T)
    dev.quick_stop()  # no friction, no command: decays from the cut on
    assert dev.sample().velocity == pytest.approx(response(3 * T), abs=EXACT)  # still tick k+4's
    at(clock, grid, k + 6, 0.9)
    assert dev.sample().velocity == pytest.approx(v_cut * math.exp(-1.75 * T / TAU_S), abs=EXACT)
    assert dev.state is PowerState.QUICK_STOP


# ------------------------------------------------------------------ the record
def test_the_record_gives_one_tick_for_same_instant_exchanges():
    dev, clock, grid = ticked()
    k = grid.index_at(clock.now) + 1
    tenths = [sum((3, 4, 22)[j % 3] for j in range(i)) for i in range(40)]  # host instants [T/10]
    for i, offset in enumerate(tenths):  # some exchanges share a tick, some ticks go unread
        clock.now = grid.instant(k) + (offset / 10 + 0.01) * T
        dev.exchange(1.0 if i % 2 else -1.0)
    rec = dev.timing()
    assert rec["tick_s"] == T and rec["commands"] == 40 and rec["reads"] == 40
    assert rec["mean_delay_s"] == pytest.approx(T, abs=1e-15)
    assert rec["min_delay_s"] == rec["max_delay_s"] == pytest.approx(T, abs=1e-15)
    ticks = [offset // 10 for offset in tenths]
    gaps = [b - a for a, b in zip(ticks, ticks[1:], strict=False)]
    assert rec["repeated_reads"] == gaps.count(0) > 0
    assert rec["skipped_ticks"] == sum(max(0, g - 1) for g in gaps) > 0


def test_the_record_pairs_a_command_with_the_next_read():
    """The ODrive way: ``c 0 u`` then ``f 0``, two requests; here the read two ticks later."""
    dev, clock, grid = ticked()
    k = grid.index_at(clock.now) + 1
    at(clock, grid, k, 0.5)
    dev.set_command(1.0)
    dev.set_command(0.5)  # replaces it before any read: one command
    at(clock, grid, k + 2, 0.5)
    dev.sample()
    at(clock, grid, k + 2, 0.9)
    dev.sample()
    rec = dev.timing()
    assert (rec["commands"], rec["reads"], rec["repeated_reads"]) == (1, 2, 1)
    # it acted before it was read
    assert rec["mean_delay_s"] == rec["min_delay_s"] == pytest.approx(-T, abs=1e-15)


def test_the_record_s_change_mean_counts_only_commands_that_change_the_value():
    """ODrive-like split requests: a command a fraction of a tick before its read acts with no
    tick or with one. A repeat acts alike from either; the change mean is over the changes."""
    dev, clock, grid = ticked()
    k = grid.index_at(clock.now) + 1
    plan = [(1.0, 0.2, 0.5), (1.0, 0.6, 0.9), (-1.0, 0.6, 0.9), (-1.0, 0.2, 0.5), (2.0, 0.2, 0.5)]
    for i, (u, sent, read) in enumerate(plan):  # (value, command's and read's share of tick k+i)
        at(clock, grid, k + i, sent)
        dev.set_command(u)
        at(clock, grid, k + i, read)
        dev.sample()
    rec = dev.timing()
    # delays [ticks]: 1 (no tick between), 1, 1, 1, 1 -- all acting from the next tick
    assert rec["commands"] == 5 and rec["changes"] == 3
    assert rec["mean_change_delay_s"] == pytest.approx(T, abs=1e-15)
    dev2, clock2, grid2 = ticked()
    k2 = grid2.index_at(clock2.now) + 1
    for i, (u, crossed) in enumerate([(1.0, True), (1.0, False), (-1.0, True), (-1.0, False)]):
        at(clock2, grid2, k2 + i, 0.9)
        dev2.set_command(u)  # a tick falls between command and read where crossed: delay 0
        at(clock2, grid2, k2 + i + (1 if crossed else 0), 0.1 if crossed else 0.95)
        dev2.sample()
    rec2 = dev2.timing()
    assert rec2["changes"] == 2 and rec2["mean_change_delay_s"] == pytest.approx(0.0, abs=1e-15)
    assert rec2["mean_delay_s"] == pytest.approx(0.5 * T, abs=1e-15)  # the repeats' ticks count here


def test_an_ethercat_sync0_samples_the_last_tick_and_its_outputs_act_from_the_next():
    """DC-synchronous EtherCAT (as tests/test_ethercat_slave.py sets it up), a 250 µs tick:
    the inputs of a SYNC0 event are the last tick's, 0x10F8 is that tick's DC system time, and
    the torque latched at event 3 acts from the tick after it."""
    import struct

    from servobench.sim_backend.faults.injector import FaultInjector
    from servobench.sim_backend.faults.spec import FaultPlan
    from servobench.sim_backend.physics.plant import Plant
    from servobench.sim_backend.servers.ethercat.coe_drive import CoeSlave

    now = [10**9]
    device = device_from_url(
        "sim://?M=0.1&B=1&seed=2&clock=real&tick=0.00025", clock=lambda: now[0] * 1e-9
    )
    grid = device.tick
    slave = CoeSlave(device, FaultInjector(device, FaultPlan("ethercat")), clock_ns=lambda: now[0])
    esc = slave.esc
    for n, (start, control) in enumerate(((0x1000, 0x26), (0x1080, 0x22))):
        esc.write(0x0800 + 8 * n, struct.pack("<HHBBBB", start, 128, control, 0, 1, 0))
    esc.write(0x0120, b"\x02\x00")
    slave.node.set_data(0x6060, 0, b"\x0a")  # CST
    slave.node.set_data(0x1C32, 1, b"\x02\x00")  # DC SYNC0
    slave.node.set_data(0x1A00, 0, b"\x00")  # TxPDO: statusword, position, velocity, torque, 0x10F8
    slave.node.set_data(0x1A00, 5, struct.pack("<I", 0x10F80040))
    slave.node.set_data(0x1A00, 0, b"\x05")
    esc.write(0x0810, struct.pack("<HHBBBB", 0x1100, 10, 0x64, 0, 1, 0))
    esc.write(0x0818, struct.pack("<HHBBBB", 0x1180, 20, 0x20, 0, 1, 0))
    start, cycle = 5_000_000, 1_000_000  # DC system time [ns]: offset 0, local time since t0
    esc.write(0x0990, struct.pack("<Q", start))
    esc.write(0x09A0, struct.pack("<I", cycle))
    esc.write(0x0981, b"\x03")
    esc.write(0x0120, b"\x04\x00")
    t0 = now[0]

    def outputs(cw: int, torque: int) -> None:
        esc.write(0x1100, struct.pack("<Hhih", cw, torque, 0, 0))

    def event(k: int) -> float:  # the loop gets to event k 0.1 ms late; its instant [s]
        now[0] = t0 + start + k * cycle + 100_000
        slave.sync0_due(now[0])
        return (t0 + start + k * cycle) * 1e-9

    esc.write(0x0120, b"\x08\x00")
    outputs(0x06, 0)
    assert esc.al_state is A_OP
    for k, cw in enumerate((0x06, 0x07, 0x0F)):
        outputs(cw, 0)
        event(k)
    outputs(0x0F, 800)  # 0.8 N m, between events 2 and 3
    acts = grid.instant(grid.index_at(event(3)) + 1)
    sampled = grid.instant(grid.index_at(event(5)))
    _sw, pos, vel, _torque, stamp = struct.unpack("<HiihQ", esc.read(0x1180, 20))
    assert abs(stamp - (sampled * 1e9 - t0)) <= 2  # 0x10F8: the tick's DC system time [ns]
    plant = Plant(PlantParams(M=0.1, B=1.0))
    plant.hold(0.8, sampled - acts)
    assert vel == pytest.approx(plant.state.v * 1e6, abs=1)  # µrad/s
    assert pos == pytest.approx(plant.state.x * 1e6, abs=1)  # µrad
    # an observer that reads the plant after event 6's instant, before the loop gets to the
    # event (the state report's thread), does not move it past the event (device.hold_before_s):
    # the event still samples its last tick, not one of the 0.35 ms after it
    now[0] = t0 + start + 6 * cycle + 300_000
    device.true_state()
    now[0] += 50_000
    slave.sync0_due(now[0])
    sampled = grid.instant(grid.index_at((t0 + start + 6 * cycle) * 1e-9))
    _sw, pos, vel, _torque, stamp = struct.unpack("<HiihQ", esc.read(0x1180, 20))
    assert abs(stamp - (sampled * 1e9 - t0)) <= 2
    plant = Plant(PlantParams(M=0.1, B=1.0))
    plant.hold(0.8, sampled - acts)
    assert vel == pytest.approx(plant.state.v * 1e6, abs=1)


# ------------------------------------------------------------------ tick 0: unchanged
REAL_NOISY = [
    (0.0, 1.2301533574825743e-05, 0.00029874553750846986),
    (0.0006999999999948159, -0.05006570461912015, -0.0009073485780986661),
    (0.001999999999995339, 0.12016557142888884, -0.0009513231822464314),
    (0.002200000000001978, 0.14858597142386895, 0.0014078160571403108),
    (0.005099999999998772, -0.10362556239802533, -0.0005300172428245039),
    (0.006100000000003547, 0.056044900280978624, 0.00042842994170566476),
    (0.006150000000005207, 0.05842930518670548, -0.0008562119403364414),
    (0.006950000000003342, 0.018919395656471882, 0.0007911917869871083),
    (0.011949999999998795, -0.01344214547285082, -0.00035305110709275465),
    (0.011949999999998795, 0.0, 0.0001045646539474635),
]
LOCKSTEP_NOISY = [
    (0.0, 1.2301533574825743e-05, 0.0),
    (0.001, -0.06362635199974366, -3.386192625171665e-05),
    (0.002, 0.07199681230478056, -2.5011073257418708e-05),
    (0.003, 0.18243134981067585, 0.00010899815334412376),
    (0.004, 0.07341982991479941, 0.00024270545766144277),
    (0.005, 0.18434193172914615, 0.00037978686253550267),
    (0.006, 0.30008505920506134, 0.0006275346035357417),
    (0.007, 0.1892235588329242, 0.0008641567715528232),
    (0.007, 0.17089934119186556, 0.0008641567715528232),
    (0.008, 0.1400572709891506, 0.001021798125435106),
]
REAL_DELAYED = [
    (0.0, 0.0, 0.0),
    (0.0006999999999948159, 0.0, 0.0),
    (0.001999999999995339, -0.039016460399610514, -9.835396005804839e-06),
    (0.002200000000001978, -0.0540849440726463, -1.915055924807345e-05),
    (0.005099999999998772, 0.036658796844179053, 0.00020341203157002875),
    (0.006100000000003547, -0.04295981448680211, 0.00019959814487601965),
    (0.006150000000005207, -0.04673556816414981, 0.00019735568164816952),
    (0.006950000000003342, -0.02554174721037783, 0.0001504174721386638),
    (0.011949999999998795, -0.015491852785730823, 4.9918527892193736e-05),
    (0.011949999999998795, -0.015491852785730823, 4.9918527892193736e-05),
]


def golden_scenario(url: str) -> list[tuple[float, float, float]]:
    """Exchanges at irregular instants, a command alone, a quick stop: what a drive gives."""
    clock = FakeClock()
    dev = device_from_url(url, clock=clock)
    dev.enable()
    out = []
    for k, dt in enumerate([0.0, 0.7e-3, 1.3e-3, 0.2e-3, 2.9e-3, 1.0e-3, 0.05e-3]):
        clock.now += dt
        s = dev.exchange(1.5 if k % 3 else -0.8)
        out.append((s.t_s, s.velocity, s.position))
    clock.now += 0.4e-3
    dev.set_command(0.3)
    clock.now += 0.4e-3
    s = dev.sample()
    out.append((s.t_s, s.velocity, s.position))
    dev.quick_stop()
    clock.now += 5e-3
    s = dev.step()
    out.append((s.t_s, s.velocity, s.position))
    out.append(dev.true_state())
    return out


@pytest.mark.parametrize(
    ("url", "expected"),
    [
        (
            "sim://?M=0.01&B=1&fc_pos=0.2&fc_neg=0.1&noise=0.01&noise_x=0.001&seed=7&clock=real",
            REAL_NOISY,
        ),
        ("sim://?M=0.01&B=1&fc_pos=0.2&fc_neg=0.1&noise=0.01&seed=7", LOCKSTEP_NOISY),
        ("sim://?M=0.01&B=1&fc_pos=0&fc_neg=0&seed=3&clock=real&delay=0.0015", REAL_DELAYED),
    ],
    ids=["real", "lockstep", "real-delay"],
)
@pytest.mark.parametrize("tick", ["", "&tick=0"])
def test_tick_zero_gives_the_numbers_of_before_bit_for_bit(url, expected, tick):
    assert golden_scenario(url + tick) == expected


def test_tick_zero_still_keeps_a_record():
    clock = FakeClock()
    dev = device_from_url("sim://?M=0.01&B=1&clock=real", clock=clock)
    assert dev.tick is None
    dev.enable()
    for _ in range(5):
        clock.now += 0.3e-3
        dev.exchange(1.0)
    assert dev.timing() == {
        "tick_s": 0.0, "phase_s": 0.0, "drift_ppm": 0.0, "commands": 5, "mean_delay_s": 0.0, "min_delay_s": 0.0,
        "max_delay_s": 0.0, "changes": 1, "mean_change_delay_s": 0.0, "reads": 5,
        "repeated_reads": 0, "skipped_ticks": 0,
    }  # fmt: skip


# ------------------------------------------------------------------ configuration
def test_a_tick_needs_the_real_clock_and_a_sane_value():
    with pytest.raises(DriveConfigError, match="needs clock=real"):
        device_from_url("sim://?M=0.01&B=1&tick=0.001")
    with pytest.raises(DriveConfigError, match="needs clock=real"):
        open_drive("sim://?M=0.01&B=1&tick=0.001")
    for bad in ("-0.001", "nan", "x"):
        with pytest.raises(DriveConfigError):
            device_from_url(f"sim://?M=0.01&B=1&clock=real&tick={bad}")
    keyword_wins = device_from_url("sim://?M=0.01&B=1&clock=real&tick=0.002", tick_s=0.001)
    assert keyword_wins.tick.tick_s == 0.001


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--clock", "lockstep", "--tick", "0.001"], "needs --clock real"),
        (["--sim", "sim://?M=0.01&tick=0.001", "--clock", "lockstep"], "needs --clock real"),
        (["--tick", "-1"], "--tick must be"),
        (["--clock", "lockstep", "--drift", "50"], "needs --clock real"),
        (["--sim", "sim://?M=0.01&drift=50", "--clock", "lockstep"], "needs --clock real"),
        (["--drift", "nan"], "--drift must be"),
    ],
)
def test_serve_sim_refuses_a_tick_or_drift_it_cannot_serve(args, message, capsys):
    assert cli_main(["serve-sim", "--transport", "modbus-tcp", *args]) != 0
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_the_tick_is_the_drives_not_the_plants():
    assert axis_of_url(parse_drive_url("sim://?M=0.1&B=1&tick=0.001")) == "sim://?B=1&M=0.1"


def test_the_in_process_drive_takes_the_tick():
    with open_drive("sim://?M=0.01&B=1&fc_pos=0&fc_neg=0&clock=real&tick=0.002") as drive:
        drive.enable()
        stamps = []
        for _ in range(20):
            stamps.append(drive.exchange(1.0)[0].t_s)
            time.sleep(0.0007)
        drive.disable()
        assert drive.device.timing()["mean_delay_s"] == pytest.approx(0.002, abs=1e-12)
    assert all(abs(t / 0.002 - round(t / 0.002)) < 1e-6 for t in stamps)


# ------------------------------------------------------------------ end to end
def test_a_served_modbus_drive_samples_on_its_own_tick(tmp_path):
    """``serve-sim --tick 0.001`` (winning over the URL's tick=0.005), ~200 FC23 at ~1 kHz."""
    state = tmp_path / "state.json"
    plant = "sim://?M=0.01&B=1&fc_pos=0&fc_neg=0&tick=0.005"
    args = ["--tick", "0.001", "--state-file", str(state)]
    with ServedSim("modbus-tcp", plant, args, clock="real") as sim:
        stamps = []
        with open_drive(sim.url + PATIENT_KEYS["modbus-tcp"]) as drive:
            assert drive.drive_clock
            drive.enable()
            deadline = time.monotonic()
            for k in range(200):
                stamps.append(drive.exchange(0.2 if k % 2 else -0.2)[0].t_s)
                deadline += 1e-3
                time.sleep(max(0.0, deadline - time.monotonic()))
            drive.disable()
    assert sim.returncode == 0, sim.stderr
    steps = [(b - a) / T for a, b in zip(stamps, stamps[1:], strict=False)]
    assert all(abs(s - round(s)) * T <= 1e-6 + 1e-9 for s in steps), steps  # one grid of ticks
    assert all(s >= 0 for s in steps)
    record = json.loads(state.read_text())["tick"]
    assert record["tick_s"] == T and 0.0 <= record["phase_s"] < T
    assert record["commands"] >= 200 and record["reads"] >= 200
    assert record["mean_delay_s"] == pytest.approx(T, abs=1e-6)
