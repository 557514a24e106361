"""The served EtherCAT slave against an independent master: SOEM (through pysoem), no servobench driver.

Each test runs a ``link_*`` function of this file in a child process inside a
user and network namespace of its own (``unshare -Urn``), with a veth pair
between SOEM and ``servobench serve-sim --transport ethercat``
(:mod:`servobench.bench.testing.ethercat_link`); the function returns what it
saw, the test judges it. The steps: scan and SII identity; SDO reads, writes
and aborts; the AL state machine's refusals; PDO remapping by SDO (complete
access, as SOEM's own example does) and the default assignment; OP; the
CiA 402 state machine through the process data; torque in and velocity out
at 1 kHz against the plant (lock-step, exact); DC system time; a real-time
slave made DC-synchronous by SOEM (0x1C32:01 = 2, SYNC0), its samples on its
SYNC0 grid (0x10F8) and on the plant driven by the outputs in force at each
event; the SM watchdog stopping the axis when the master falls silent.

The cyclic run lasts :data:`RUN_S` (3 s, 3000 cycles at 1 kHz): the issue asks
10 s, which ``benchmarks/ethercat_soem.py`` runs; three seconds hold the same
checks within the suite's budget on a shared two-core machine.
"""

from __future__ import annotations

import struct
import time

import numpy as np
import pytest

from servobench.bench.testing.ethercat_link import link_unavailable, run_on_link
from servobench.sim_backend.physics.plant import Plant, PlantParams, simulate

pytestmark = pytest.mark.slow  # 3 s of 1 kHz cycles and the watchdog, in child processes: 15 s


@pytest.fixture(autouse=True, scope="module")
def _link() -> None:
    """No private link is a failure to fix (run as root, or allow user namespaces), never a skip."""
    why = link_unavailable()
    if why is not None:
        pytest.fail(f"no private EtherCAT link: {why}")

SIM = "sim://?M=0.1&B=1&fc_pos=0.2&fc_neg=0.15"
PARAMS = PlantParams(M=0.1, B=1.0, coulomb_pos=0.2, coulomb_neg=0.15)
RUN_S = 3.0
#: The SM watchdog of the watchdog test [ms]: longer than a busy host's stalls while it streams.
WATCHDOG_MS = 200
CYCLE_S = 0.001
#: How long the master waits for a frame to come back [µs]: "the slave answered" on a
#: loaded machine (a Python slave on a shared core is sometimes late by milliseconds).
RECEIVE_US = 500_000
#: Vendor id, product code and revision in the served drive's EDS (0x1018) and so its SII.
IDENTITY = (0x00000000, 0x00000402, 0x00010000)
# CiA 301 abort codes SOEM must see.
NO_OBJECT, NO_SUBINDEX, READ_ONLY, DEVICE_STATE = 0x06020000, 0x06090011, 0x06010002, 0x08000022


def _open(iface: str):
    import pysoem

    # SOEM's register and scan timeouts (2 ms, 20 ms) fit an ESC answering in microseconds;
    # a Python slave on a loaded two-core machine is given 20 ms and 200 ms
    pysoem.settings.timeouts.ret = 20_000
    pysoem.settings.timeouts.safe = 200_000
    master = pysoem.Master()
    master.open(iface)
    return pysoem, master


def _remap_with_time_stamp(slave) -> None:
    """TxPDO 0x1A00: statusword, position, velocity, torque, drive time stamp 0x1013 (CA writes)."""
    entries = [0x60410010, 0x60640020, 0x606C0020, 0x60770010, 0x10130020]
    slave.sdo_write(0x1C13, 0, struct.pack("<BxH", 1, 0x1A00), ca=True)
    slave.sdo_write(
        0x1A00, 0, struct.pack("<Bx" + "I" * len(entries), len(entries), *entries), ca=True
    )


def _to_op(pysoem, master, cycles: int = 200) -> int:
    master.send_processdata()
    master.receive_processdata(RECEIVE_US)
    master.state = pysoem.OP_STATE
    master.write_state()
    for _ in range(cycles):
        master.send_processdata()
        master.receive_processdata(RECEIVE_US)
        if master.state_check(pysoem.OP_STATE, 2000) == pysoem.OP_STATE:
            break
    return master.read_state()


def _remap_dc_synchronous(slave) -> None:
    """TxPDO 0x1A00 with the timestamp object 0x10F8, and 0x1C32:01 = 2 (DC SYNC0), in PRE-OP."""
    entries = [0x60410010, 0x60640020, 0x606C0020, 0x60770010, 0x10F80040]
    slave.sdo_write(0x1C13, 0, struct.pack("<BxH", 1, 0x1A00), ca=True)
    slave.sdo_write(
        0x1A00, 0, struct.pack("<Bx" + "I" * len(entries), len(entries), *entries), ca=True
    )
    slave.sdo_write(0x1C32, 1, struct.pack("<H", 2))


# ------------------------------------------------------------ link functions
def link_dc_synchronous(iface: str, url: str) -> dict:
    """A real-time slave, DC-synchronous: CST at 1 kHz, 0x10F8 and the frame's DC time read."""
    pysoem, master = _open(iface)
    out: dict = {}
    try:
        master.config_init()
        slave = master.slaves[0]
        out["supported"] = struct.unpack("<H", slave.sdo_read(0x1C32, 4))[0]
        slave.sdo_write(0x6060, 0, struct.pack("<b", 10))
        slave.config_func = lambda pos: _remap_dc_synchronous(master.slaves[pos])
        master.config_map()
        slave.set_watchdog("processdata", 2000)
        out["has_dc"] = bool(master.config_dc())
        slave.dc_sync(True, int(CYCLE_S * 1e9))
        out["sync0"] = [struct.unpack("<Q", slave._fprd(0x0990, 8))[0],
                        struct.unpack("<I", slave._fprd(0x09A0, 4))[0]]  # fmt: skip
        out["op"] = _to_op(pysoem, master)
        while master.dc_time < out["sync0"][0] + 2 * out["sync0"][1]:  # SYNC0 starts later
            master.send_processdata()
            master.receive_processdata(RECEIVE_US)
            time.sleep(CYCLE_S)
        for cw in (0x06, 0x07, 0x0F):
            for _ in range(5):
                slave.output = struct.pack("<Hh4xh", cw, 0, 0)
                master.send_processdata()
                master.receive_processdata(RECEIVE_US)
                time.sleep(CYCLE_S)  # the outputs take force at the next SYNC0
        n = int(2.0 / CYCLE_S)
        u_permille = np.where((np.arange(n) // 500) % 2 == 0, 600, -600)
        rows, dc = [], []
        deadline = time.monotonic()
        for k in range(n):
            deadline += CYCLE_S
            slave.output = struct.pack("<Hh4xh", 0x0F, int(u_permille[k]), 0)
            master.send_processdata()
            master.receive_processdata(RECEIVE_US)
            rows.append(struct.unpack("<HiihQ", slave.input))
            dc.append(master.dc_time)
            time.sleep(max(0.0, deadline - time.monotonic()))
        out["rows"], out["dc"], out["u"] = rows, dc, u_permille.tolist()
        master.state = pysoem.INIT_STATE
        master.write_state()
    finally:
        master.close()
    return out


def link_bringup(iface: str, url: str) -> dict:
    pysoem, master = _open(iface)
    out: dict = {"url": url}
    try:
        out["found"] = master.config_init()
        slave = master.slaves[0]
        out["identity"] = [slave.man, slave.id, slave.rev]
        out["name"] = slave.name
        out["device_type"] = struct.unpack("<I", slave.sdo_read(0x1000, 0))[0]
        out["modes"] = struct.unpack("<I", slave.sdo_read(0x6502, 0))[0]
        out["device_name"] = slave.sdo_read(0x1008, 0).decode()
        out["sm_types"] = list(slave.sdo_read(0x1C00, 0, ca=True))
        out["rx_assign"] = slave.sdo_read(0x1C12, 0, ca=True).hex()
        out["rx_map"] = slave.sdo_read(0x1600, 0, ca=True).hex()
        aborts = {}
        for name, call in (
            ("no_object", lambda: slave.sdo_read(0x2345, 0)),
            ("no_subindex", lambda: slave.sdo_read(0x1018, 9)),
            ("read_only", lambda: slave.sdo_write(0x6041, 0, b"\x00\x00")),
            ("length", lambda: slave.sdo_write(0x6071, 0, b"\x01\x02\x03\x04")),
        ):
            try:
                call()
                aborts[name] = 0
            except pysoem.SdoError as err:
                aborts[name] = err.abort_code
        out["aborts"] = aborts
        slave.sdo_write(0x6060, 0, struct.pack("<b", 10))
        out["mode"] = struct.unpack("<b", slave.sdo_read(0x6061, 0))[0]
        # PRE-OP -> OP skips SAFE-OP: refused with 0x0011 and the error flag, then acknowledged
        slave.state = pysoem.OP_STATE
        slave.write_state()
        slave.state_check(pysoem.OP_STATE, 20_000)
        master.read_state()
        out["refused"] = [slave.state, slave.al_status]
        slave.state = pysoem.PREOP_STATE | 0x10
        slave.write_state()
        out["acknowledged"] = slave.state_check(pysoem.PREOP_STATE, 50_000)
        out["iomap"] = master.config_map()
        out["safeop"] = master.state_check(pysoem.SAFEOP_STATE, 50_000)
        out["sizes"] = [len(slave.output), len(slave.input)]
        try:
            slave.sdo_write(0x1C12, 0, b"\x00")
            out["assign_in_safeop"] = 0
        except pysoem.SdoError as err:
            out["assign_in_safeop"] = err.abort_code
        out["op"] = _to_op(pysoem, master)
        master.send_processdata()
        out["wkc"] = [master.receive_processdata(RECEIVE_US), master.expected_wkc]
    finally:
        master.close()
    return out


def link_cyclic(iface: str, url: str) -> dict:
    """CST at 1 kHz: a torque square wave in, velocity and position out, with DC."""
    pysoem, master = _open(iface)
    out: dict = {}
    try:
        master.config_init()
        slave = master.slaves[0]
        slave.sdo_write(0x6060, 0, struct.pack("<b", 10))
        slave.config_func = lambda pos: _remap_with_time_stamp(master.slaves[pos])
        master.config_map()
        slave.set_watchdog("processdata", 2000)  # not this test's subject: no trip on a busy host
        out["has_dc"] = bool(master.config_dc())
        slave.dc_sync(True, int(CYCLE_S * 1e9))
        out["op"] = _to_op(pysoem, master)
        states = []
        for cw in (0x06, 0x07, 0x0F):  # shutdown, switch on, enable operation (2, 3, 4)
            for _ in range(5):
                slave.output = struct.pack("<Hh4xh", cw, 0, 0)
                master.send_processdata()
                master.receive_processdata(RECEIVE_US)
            states.append(struct.unpack_from("<H", slave.input)[0])
        out["statuswords"] = states
        n = int(RUN_S / CYCLE_S)
        u_permille = np.where((np.arange(n) // 500) % 2 == 0, 600, -600)
        rows, dc, wkcs = [], [], []
        deadline = start = time.monotonic()
        for k in range(n):
            deadline += CYCLE_S
            slave.output = struct.pack("<Hh4xh", 0x0F, int(u_permille[k]), 0)
            master.send_processdata()
            wkcs.append(master.receive_processdata(RECEIVE_US))
            rows.append(struct.unpack("<HiihI", slave.input))
            dc.append(master.dc_time)
            time.sleep(max(0.0, deadline - time.monotonic()))
        out["elapsed_s"] = time.monotonic() - start
        out["rows"] = rows
        out["u"] = u_permille.tolist()
        out["dc"] = dc
        out["wkc"] = [int(np.sum(np.array(wkcs) == master.expected_wkc)), len(wkcs)]
        slave.output = struct.pack("<Hh4xh", 0x06, 0, 0)
        master.send_processdata()
        master.receive_processdata(RECEIVE_US)
        master.state = pysoem.INIT_STATE
        master.write_state()
    finally:
        master.close()
    return out


def link_watchdog(iface: str, url: str) -> dict:
    """Enable, drive, then fall silent: the SM watchdog must stop the axis."""
    pysoem, master = _open(iface)
    out: dict = {}
    try:
        master.config_init()
        slave = master.slaves[0]
        slave.sdo_write(0x6060, 0, struct.pack("<b", 10))
        emergencies = out["emergencies"] = []
        slave.add_emergency_callback(lambda e: emergencies.append([e.error_code, e.error_reg]))
        master.config_map()
        slave.set_watchdog("processdata", WATCHDOG_MS)
        out["watchdog_ms"] = slave.get_watchdog("processdata")
        out["op"] = _to_op(pysoem, master)
        for cw, torque, cycles in ((0x06, 0, 5), (0x07, 0, 5), (0x0F, 0, 5), (0x0F, 500, 300)):
            for _ in range(cycles):
                slave.output = struct.pack("<Hh4xh", cw, torque, 0)
                master.send_processdata()
                master.receive_processdata(RECEIVE_US)
                time.sleep(CYCLE_S)  # a real-time slave: the axis moves in wall-clock time
        out["moving"] = struct.unpack_from("<Hii", slave.input)
        time.sleep(WATCHDOG_MS / 1000 + 0.8)  # silent: the watchdog trips, the axis coasts down
        master.read_state()
        out["al"] = [slave.state, slave.al_status]
        out["wd_counter"] = slave._fprd(0x0442, 1)[0]
        out["error_code"] = struct.unpack("<H", slave.sdo_read(0x603F, 0))[0]
        out["statusword"] = struct.unpack("<H", slave.sdo_read(0x6041, 0))[0]
        out["positions"] = [struct.unpack("<i", slave.sdo_read(0x6064, 0))[0]]
        time.sleep(0.2)
        out["positions"].append(struct.unpack("<i", slave.sdo_read(0x6064, 0))[0])
    finally:
        master.close()
    return out


# --------------------------------------------------------------------- tests
@pytest.fixture(scope="module")
def bringup() -> dict:
    return run_on_link(__file__, "link_bringup", SIM)


def test_scan_and_sii_identity(bringup: dict) -> None:
    assert bringup["url"] == "ethercat://ecmaster?slave=1"  # the peer of the served end
    assert bringup["found"] == 1
    assert bringup["identity"] == list(IDENTITY)
    assert bringup["name"] == "servobench CiA 402 drive"


def test_sdo_reads_say_cia402(bringup: dict) -> None:
    assert bringup["device_type"] & 0xFFFF == 402  # CiA 402 device profile
    assert bringup["modes"] & (1 << 9) and bringup["modes"] & (1 << 7)  # CST and CSP
    assert bringup["device_name"] == "servobench CiA 402 drive"
    assert bringup["sm_types"] == [4, 0, 1, 2, 3, 4]  # CA: count, padding, types
    assert bringup["rx_assign"] == "0100" + "0016" + "0000" * 3  # 1 PDO: 0x1600
    entries = struct.unpack("<Bx8I", bytes.fromhex(bringup["rx_map"]))
    assert entries[0] == 4
    assert entries[1:5] == (0x60400010, 0x60710010, 0x607A0020, 0x60B20010)


def test_sdo_aborts_are_cia301_codes(bringup: dict) -> None:
    assert bringup["aborts"] == {
        "no_object": NO_OBJECT,
        "no_subindex": NO_SUBINDEX,
        "read_only": READ_ONLY,
        "length": 0x06070010,
    }
    assert bringup["assign_in_safeop"] == DEVICE_STATE
    assert bringup["mode"] == 10


def test_al_refuses_a_skipped_state_then_takes_the_acknowledge(bringup: dict) -> None:
    assert bringup["refused"] == [0x02 | 0x10, 0x0011]
    assert bringup["acknowledged"] == 0x02


def test_default_assignment_runs_in_op(bringup: dict) -> None:
    assert bringup["sizes"] == [
        10,
        12,
    ]  # cw, torque, position, offset | sw, position, velocity, torque
    assert bringup["iomap"] == 22
    assert bringup["safeop"] == 0x04
    assert bringup["op"] == 0x08
    assert bringup["wkc"] == [3, 3]  # LRW: outputs written (2) + inputs read (1)


def test_cyclic_torque_in_velocity_out_against_the_plant() -> None:
    # lock-step: exact, cycle by cycle
    out = run_on_link(__file__, "link_cyclic", SIM, ["--clock", "lockstep"])
    assert out["op"] == 0x08 and out["has_dc"]
    # statusword: ready to switch on, switched on, operation enabled (CiA 402 table 30)
    assert [sw & 0x6F for sw in out["statuswords"]] == [0x21, 0x23, 0x27]
    rows = np.array(out["rows"], dtype=float)
    good, total = out["wkc"]
    assert good == total, f"{total - good} of {total} frames with a wrong working counter"
    u = np.array(out["u"]) / 1000.0  # per mille of the rated torque 1 N m
    v_ref, x_ref = simulate(u, 1.0 / CYCLE_S, PARAMS)
    assert np.max(np.abs(v_ref)) > 0.3  # the axis moves both ways, past the friction
    np.testing.assert_allclose(rows[:, 2] * 1e-6, v_ref, atol=2e-6)  # µrad/s
    np.testing.assert_allclose(rows[:, 1] * 1e-6, x_ref, atol=2e-6)  # µrad
    np.testing.assert_allclose(rows[1:, 3] / 1000.0, u[:-1])  # torque actual: the cycle before
    np.testing.assert_array_equal(np.diff(rows[:, 4]), 1000)  # drive time stamp [µs]
    dc = np.array(out["dc"], dtype=float)
    assert np.all(np.diff(dc) > 0)  # DC system time read every frame (FRMW)
    # the DC clock runs in real time: its span over the run is the host's (whatever the load)
    assert (dc[-1] - dc[0]) * 1e-9 == pytest.approx(out["elapsed_s"], abs=0.05)


def test_dc_synchronous_slave_samples_on_its_sync0_grid_in_real_time() -> None:
    """SOEM sets DC SYNC0 and 0x1C32:01 = 2 on a real-time slave: each sample is taken at a
    SYNC0 event (0x10F8), the last before the frame, and the plant from the first sample, driven
    at each event by the outputs last received before it, gives every later one."""
    out = run_on_link(__file__, "link_dc_synchronous", SIM, ["--clock", "real"])
    assert out["supported"] & 0x0004 and out["has_dc"] and out["op"] == 0x08
    start, cycle = out["sync0"]
    assert cycle == 1_000_000
    rows = np.array(out["rows"], dtype=np.int64)
    stamp, dc = rows[:, 4], np.array(out["dc"], dtype=np.int64)
    assert np.all((stamp - start) % cycle == 0)  # on the grid, whatever the host's timing
    assert np.all((stamp <= dc) & (stamp > dc - cycle))  # the last event before the frame
    assert np.all(rows[:, 0] & 0x6F == 0x27)  # operation enabled throughout
    # the command in force from each event: the outputs of the last frame before it
    u = np.array(out["u"]) / 1000.0
    events = np.arange(stamp[0], stamp[-1] + cycle, cycle)
    last_frame = np.searchsorted(dc, events, side="left") - 1
    u_events = np.where(last_frame >= 0, u[np.maximum(last_frame, 0)], 0.0)
    plant = Plant(PARAMS)
    plant.reset(rows[0, 2] * 1e-6, rows[0, 1] * 1e-6)
    v_ref, x_ref = plant.step_block(u_events, cycle * 1e-9)
    at = (stamp - stamp[0]) // cycle
    off = np.flatnonzero(np.abs(rows[:, 2] * 1e-6 - v_ref[at]) > 1e-5)
    around = range(max(0, off[0] - 3), min(len(rows), off[0] + 3)) if off.size else ()
    frames = [(k, int(u[k] * 1000), int(dc[k] - start), int(stamp[k] - start)) for k in around]
    note = f"first frames off (k, u permille, DC time, its sample's SYNC0) [ns]: {frames}"
    np.testing.assert_allclose(rows[:, 2] * 1e-6, v_ref[at], atol=1e-5, err_msg=note)  # µrad/s
    np.testing.assert_allclose(rows[:, 1] * 1e-6, x_ref[at], atol=1e-5, err_msg=note)  # µrad
    assert np.max(np.abs(v_ref)) > 0.3


def test_sm_watchdog_stops_the_axis_when_the_master_falls_silent() -> None:
    out = run_on_link(__file__, "link_watchdog", SIM)
    assert out["watchdog_ms"] == pytest.approx(WATCHDOG_MS)
    assert out["op"] == 0x08
    assert out["moving"][0] & 0x6F == 0x27 and out["moving"][2] > 100_000  # enabled, > 0.1 rad/s
    assert out["al"] == [0x04 | 0x10, 0x001B]  # SAFE-OP + error, sync manager watchdog
    assert out["wd_counter"] == 1
    assert out["error_code"] == 0x8130
    assert out["emergencies"] == [[0x8130, 0x11]]  # CoE emergency: generic + communication
    assert out["statusword"] & 0x4F == 0x08  # FAULT
    assert out["positions"][0] == out["positions"][1]  # torque off: coasted to rest
