"""Served drives that behave like real ones in time (issue 22 §1), on every transport.

A host on the real protocol stack latches a constant command and then reads
the feedback at irregular instants, ~3.3 cycles apart. The plant has no
friction (pole -100 rad/s), so its step response ``v(t) = 1 - exp(-t/tau)``
is known by hand. Whatever the machine's load, each sample was taken
between the host's request and the answer, and the command latched between
the first request and its answer: the velocity must lie between the
response at the shortest and at the longest of these spans. A lock-step
drive (one cycle per read) lies far below it, which the last case shows.

Where the drive has a time stamp, its stamps are its own clock: consecutive
samples obey the exact first-order propagation over the stamped interval,
the intervals lie within the host's brackets (wall time, not cycle counts)
and the stamps are whole microseconds. Independent peers check the encodings:
the canopen library as a CiA 301 master (0x1013 UNSIGNED32 µs, by SDO and in
a TPDO it maps itself), pyModbusTCP reading the raw timestamp register; and
the drives served with ``--no-timestamp`` have neither.
"""

from __future__ import annotations

import math
import os
import random
import subprocess
import sys
import time

import canopen
import pytest
from canopen.sdo import SdoAbortedError
from pyModbusTCP.client import ModbusClient

from servobench.bench.testing.served import ServedSim
from servobench.bench.testing.served_canopen import served, station
from servobench.bench.testing.served_modbus import host_port, served_modbus
from servobench.drivers.canopen.link import load_eds
from servobench.drivers.registry import open_drive
from servobench.errors import DriveConfigError

TAU_S = 0.01
PLANT = "sim://?M=0.01&B=1&fc_pos=0&fc_neg=0"
WAIT_S = 3.3e-3
READS = 12
#: What each transport reports velocity in steps of (CANopen: the EDS's 0x606C factor).
RESOLUTION = {"canopen": 2e-6, "modbus-tcp": 2e-6, "modbus-rtu": 2e-6, "serial": 2e-6}
CASES = [
    ("canopen", ()),
    ("canopen", ("--no-timestamp",)),
    ("modbus-tcp", ()),
    ("modbus-tcp", ("--no-timestamp",)),
    ("modbus-rtu", ()),
    ("serial", ()),
]


def response(t_s: float) -> float:
    return 1.0 - math.exp(-max(t_s, 0.0) / TAU_S)


def bracketed_reads(url: str, wait_s: float = WAIT_S):
    """``[(before, after, feedback)]``: a command of 1 latched by the first exchange, then reads."""
    rows = []
    with open_drive(url) as drive:
        drive.set_cycle(1e-3)
        drive.enable()
        for _ in range(3):
            drive.exchange(0.0)  # at rest, enabled
        for _ in range(READS + 1):
            before = time.monotonic()
            fb, _ = drive.exchange(1.0)
            rows.append((before, time.monotonic(), fb))
            time.sleep(wait_s)
        drive.disable()
    return rows


def check_wall_clock_motion(rows, tol: float) -> None:
    b0, a0, _ = rows[0]
    for before, after, fb in rows:
        low, high = response(before - a0), response(after - b0)
        assert low - tol <= fb.velocity <= high + tol, (before - b0, fb.velocity, low, high)


@pytest.mark.parametrize(("transport", "args"), CASES, ids=[t if t == "serial" else f"{t}-{'no-timestamp' if a else 'stamped'}" for t, a in CASES])
def test_feedback_is_the_plant_integrated_in_wall_clock_time(transport, args):
    with ServedSim(transport, PLANT, args, clock="real") as sim:
        if args:  # the printed URL reaches the drive without a time stamp
            assert ("eds=cia402-nostamp" if transport == "canopen" else "map=servobench-sim-nostamp") in sim.url
        rows = bracketed_reads(sim.url)
    assert sim.returncode == 0, sim.stderr
    check_wall_clock_motion(rows, RESOLUTION[transport])
    assert rows[-1][2].velocity > response(READS * WAIT_S) - 0.01  # it moved as 12 waits, not 12 cycles
    if args or transport == "serial":
        return
    stamps = [fb.t_s for _, _, fb in rows]
    for (b1, a1, f1), (b2, a2, f2) in zip(rows, rows[1:], strict=False):
        dt = f2.t_s - f1.t_s
        assert b2 - a1 - 2e-6 <= dt <= a2 - b1 + 2e-6  # wall time between the samples
        predicted = 1.0 + (f1.velocity - 1.0) * math.exp(-dt / TAU_S)
        assert f2.velocity == pytest.approx(predicted, abs=3e-4)
    assert all(abs(t * 1e6 - round(t * 1e6)) < 1e-3 for t in stamps)  # whole microseconds


@pytest.mark.parametrize("transport", ["canopen", "modbus-tcp", "modbus-rtu"])
def test_each_stamped_sample_follows_from_the_last_under_the_command_sent_with_it(transport):
    """The log's model holds exactly: ``v[k]`` sampled at ``t[k]``, then ``u[k]`` acts until ``t[k+1]``.

    The command flips at every exchange and the host waits irregularly, so a
    command that took force before its sample (or after) by even 10 µs shows
    as 2e-3 [rad/s] here; the stamps and the velocity are good to about 2e-4.
    """
    with ServedSim(transport, PLANT, clock="real") as sim:
        assert worst_one_step_error(sim.url) < 3e-4


def test_sim_clock_real_samples_follow_the_log_model_exactly():
    assert worst_one_step_error(PLANT + "&clock=real") < 1e-9  # in-process: exact stamps


def worst_one_step_error(url: str) -> float:
    """Flip the command at every exchange, wait irregularly; the worst one-step prediction error."""
    rng = random.Random(3)
    rows = []
    with open_drive(url) as drive:
        drive.set_cycle(1e-3)
        drive.enable()
        for k in range(60):
            rows.append(drive.exchange(1.0 if k % 2 else -1.0))
            time.sleep(rng.uniform(0.5e-3, 3e-3))
        drive.disable()
    worst = 0.0
    for (f1, u1), (f2, _) in zip(rows, rows[1:], strict=False):
        predicted = u1 + (f1.velocity - u1) * math.exp(-(f2.t_s - f1.t_s) / TAU_S)
        worst = max(worst, abs(f2.velocity - predicted))
    return worst


def test_a_lockstep_drive_sees_one_cycle_per_read_however_long_the_host_waits():
    with ServedSim("modbus-tcp", PLANT, clock="lockstep") as sim:
        rows = bracketed_reads(sim.url)
    velocities = [fb.velocity for _, _, fb in rows]
    assert velocities == pytest.approx([response(k * 1e-3) for k in range(len(rows))], abs=2e-6)
    with pytest.raises(AssertionError):  # which the wall-clock check tells apart
        check_wall_clock_motion(rows, RESOLUTION["modbus-tcp"])


# ------------------------------------------------------------ independent peers
def test_0x1013_is_unsigned32_microseconds_of_the_drive_clock_by_sdo_and_tpdo():
    """canopen as a CiA 301 master: 0x1013 read by SDO and mapped in a TPDO it configures."""
    with served(PLANT, clock="real") as (device, url), station(url) as node:
        assert node.object_dictionary[0x1013].data_type == canopen.objectdictionary.UNSIGNED32
        b1 = time.monotonic()
        raw1 = node.sdo.upload(0x1013, 0)
        a1 = time.monotonic()
        time.sleep(0.05)
        b2 = time.monotonic()
        raw2 = node.sdo.upload(0x1013, 0)
        a2 = time.monotonic()
        assert len(raw1) == len(raw2) == 4
        us1, us2 = int.from_bytes(raw1, "little"), int.from_bytes(raw2, "little")
        assert (b2 - a1) * 1e6 - 1 <= us2 - us1 <= (a2 - b1) * 1e6 + 1
        node.tpdo.read()
        tpdo = node.tpdo[1]
        tpdo.clear()
        tpdo.add_variable(0x1013)
        tpdo.trans_type = 1
        tpdo.enabled = True
        node.nmt.state = "PRE-OPERATIONAL"
        tpdo.save()
        node.nmt.state = "OPERATIONAL"
        time.sleep(0.05)
        stamps = []
        for _ in range(3):
            before = time.monotonic()
            node.network.sync.transmit()
            tpdo.wait_for_reception(2.0)
            stamps.append((before, time.monotonic(), tpdo[0].raw))
            time.sleep(0.02)
        node.nmt.state = "PRE-OPERATIONAL"
    (b1, a1, s1), (b2, a2, s2), _ = stamps
    assert (b2 - a1) * 1e6 - 1 <= s2 - s1 <= (a2 - b1) * 1e6 + 1  # wall time, not SYNC counts


def test_the_drive_without_a_time_stamp_has_no_0x1013():
    with served(PLANT, clock="real", eds="cia402-nostamp") as (_, url), station(url) as node:
        with pytest.raises(SdoAbortedError) as err:
            node.sdo.upload(0x1013, 0)
        assert err.value.code == 0x06020000  # object does not exist in the object dictionary
        assert node.sdo.upload(0x6041, 0)  # the rest answers
    full, bare = load_eds(2), load_eds(2, "cia402-nostamp")
    assert {o.index for o in full.values()} - {o.index for o in bare.values()} == {0x1013}
    assert {o.index for o in bare.values()} < {o.index for o in full.values()}


def test_the_modbus_timestamp_register_counts_microseconds_and_is_absent_without_it():
    with served_modbus("modbus-tcp", PLANT, clock="real") as (_, url):
        host, port = host_port(url)
        client = ModbusClient(host=host, port=port, unit_id=1, auto_open=True, timeout=2.0)
        b1 = time.monotonic()
        w1 = client.read_holding_registers(0x22, 2)
        a1 = time.monotonic()
        time.sleep(0.05)
        b2 = time.monotonic()
        w2 = client.read_holding_registers(0x22, 2)
        a2 = time.monotonic()
        client.close()
    us1, us2 = (w[0] << 16 | w[1] for w in (w1, w2))  # uint32, big-endian words (the map)
    assert (b2 - a1) * 1e6 - 1 <= us2 - us1 <= (a2 - b1) * 1e6 + 1
    with served_modbus("modbus-tcp", PLANT, clock="real", map="servobench-sim-nostamp") as (_, url):
        host, port = host_port(url)
        client = ModbusClient(host=host, port=port, unit_id=1, auto_open=True, timeout=2.0)
        assert client.read_holding_registers(0x22, 2) is None
        assert client.last_except == 2  # illegal data address: the drive has no such register
        assert client.read_holding_registers(0x24, 4) is not None  # velocity and position answer
        client.close()


# ---------------------------------------------------------------- serve-sim
def test_real_time_is_the_default_and_rt_priority_is_asked_for_and_reported():
    with ServedSim("modbus-tcp", PLANT, ["--rt-priority", "5"]) as sim:  # serve-sim's default clock
        assert sim.url.startswith("modbus+tcp://")
        policy = os.sched_getscheduler(sim.proc.pid)
        rows = bracketed_reads(sim.url)
    check_wall_clock_motion(rows, RESOLUTION["modbus-tcp"])
    assert "serve-sim: real-time priority: " in sim.stderr
    if "SCHED_FIFO 5" in sim.stderr:
        assert policy == os.SCHED_FIFO
    else:
        assert "not granted" in sim.stderr and policy != os.SCHED_FIFO


def test_no_timestamp_refuses_an_object_dictionary_that_has_one():
    out = subprocess.run(
        [sys.executable, "-m", "servobench", "serve-sim", "--transport", "canopen",
         "--eds", "cia402", "--no-timestamp"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert out.returncode != 0 and out.stdout == ""
    assert out.stderr.startswith("servobench: error: --no-timestamp: --eds cia402 has a time stamp")
    assert "Traceback" not in out.stderr


# ---------------------------------------------------------------- sim://
def test_sim_clock_real_integrates_wall_clock_time_in_process():
    with open_drive(PLANT + "&clock=real") as drive:
        assert drive.realtime and not drive.supports_block
    rows = bracketed_reads(PLANT + "&clock=real")
    check_wall_clock_motion(rows, 1e-12)
    with pytest.raises(DriveConfigError, match="sim clock must be"):
        open_drive(PLANT + "&clock=fast")


def test_a_vanished_host_is_stopped_by_the_watchdog_and_the_next_session_finds_the_axis_at_rest():
    """Real time end to end: the watchdog trips in wall-clock time, the axis coasts to rest
    while nobody polls, and the next session's drive clock starts again from 0."""
    with ServedSim("modbus-tcp", PLANT, clock="real") as sim:
        url = sim.url + "&watchdog=0.2"
        gone = open_drive(url)
        gone.open()
        gone.set_cycle(1e-3)
        gone.enable()
        for _ in range(50):
            moving = gone.exchange(1.0)[0]
            time.sleep(1e-3)
        gone._close()  # the link drops: no stop, no disable
        time.sleep(0.6)  # watchdog 0.2 s, then a coast of a few tau
        with open_drive(url) as fresh:
            assert fresh.fault_code() == 0x8130  # the watchdog's fault
            fresh.reset_fault()
            first = fresh.read()
            time.sleep(0.1)
            second = fresh.read()
    assert moving.velocity > 0.5
    assert first.velocity == 0.0 and second.velocity == 0.0  # at rest (no friction: exactly 0 in µrad/s)
    assert second.position == first.position > moving.position
    assert 0.1 - 0.01 <= second.t_s - first.t_s <= 0.5  # wall time between two reads
    assert first.t_s < 0.5  # the session restarted the drive clock
