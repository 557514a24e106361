"""``serve-sim --profile``: the served slave's real-drive quirks, as SOEM (pysoem) sees them.

Each test runs a ``link_*`` function of this file against ``servobench serve-sim
--transport ethercat --profile ...`` on a private veth link
(:mod:`servobench.bench.testing.ethercat_link`, as ``tests/test_ethercat_soem.py``);
the expectations are CiA 301 abort codes and CiA 402 statuswords, not read
from the modules under test.
"""

from __future__ import annotations

import struct

import pytest

from servobench.bench.testing.ethercat_link import link_unavailable, run_on_link

pytestmark = pytest.mark.slow  # one served slave per test, each in its own namespace

SIM = "sim://?M=0.1&B=1&fc_pos=0.2&fc_neg=0.15"
RECEIVE_US = 500_000
# CiA 301 abort codes.
UNSUPPORTED_ACCESS, READ_ONLY, VALUE_RANGE = 0x06010000, 0x06010002, 0x06090030
# CiA 402 statusword (mask 0x6F): operation enabled, quick stop active; (mask 0x4F) switch on disabled.
ENABLED, QUICK_STOP_ACTIVE, SWITCH_ON_DISABLED = 0x27, 0x07, 0x40
TXPDO = [0x60410010, 0x60640020, 0x606C0020, 0x60770010]  # sw, position, velocity, torque actual
#: Not the default mapping of 0x1A00 (four entries): statusword, position, torque actual.
REMAP = [0x60410010, 0x60640020, 0x60770010]


@pytest.fixture(autouse=True, scope="module")
def _link() -> None:
    why = link_unavailable()
    if why is not None:
        pytest.fail(f"no private EtherCAT link: {why}")


def _open(iface: str):
    import pysoem

    pysoem.settings.timeouts.ret = 20_000
    pysoem.settings.timeouts.safe = 200_000
    master = pysoem.Master()
    master.open(iface)
    master.config_init()
    return pysoem, master, master.slaves[0]


def _abort(pysoem, call) -> int:
    """The abort code ``call`` (an SDO transfer) got, 0 when it succeeded."""
    try:
        call()
    except pysoem.SdoError as err:
        return err.abort_code
    return 0


def _map_entry_by_entry(slave, index: int, entries: list[int]) -> None:
    slave.sdo_write(index, 0, b"\x00")
    for sub, entry in enumerate(entries, start=1):
        slave.sdo_write(index, sub, struct.pack("<I", entry))
    slave.sdo_write(index, 0, bytes([len(entries)]))


def _controlwords_by_sdo(slave, words) -> list[int]:
    """Each controlword written to 0x6040 by SDO, then the statusword 0x6041 read by SDO."""
    out = []
    for cw in words:
        slave.sdo_write(0x6040, 0, struct.pack("<H", cw))
        out.append(struct.unpack("<H", slave.sdo_read(0x6041, 0))[0])
    return out


# ------------------------------------------------------------ link functions
def link_no_cst(iface: str, url: str) -> dict:
    """No CST: 0x6502, 0x6060 = 10 refused; CSP with the torque offset mapped, in OP."""
    pysoem, master, slave = _open(iface)
    out: dict = {}
    try:
        out["modes"] = struct.unpack("<I", slave.sdo_read(0x6502, 0))[0]
        out["cst"] = _abort(pysoem, lambda: slave.sdo_write(0x6060, 0, struct.pack("<b", 10)))
        out["csp"] = _abort(pysoem, lambda: slave.sdo_write(0x6060, 0, struct.pack("<b", 8)))
        out["cycle_time"] = _abort(pysoem, lambda: slave.sdo_write(0x1C32, 2, b"\x40\x42\x0f\x00"))

        def remap(pos: int) -> None:  # cw, target position, torque offset | TXPDO
            _map_entry_by_entry(master.slaves[pos], 0x1600, [0x60400010, 0x607A0020, 0x60B20010])
            _map_entry_by_entry(master.slaves[pos], 0x1A00, TXPDO)

        slave.config_func = remap
        master.config_map()
        master.send_processdata()
        master.receive_processdata(RECEIVE_US)
        master.state = pysoem.OP_STATE
        master.write_state()
        rows = []
        for cw, offset, cycles in ((0x06, 0, 5), (0x07, 0, 5), (0x0F, 0, 5), (0x0F, 300, 2)):
            for _ in range(cycles):
                slave.output = struct.pack("<Hih", cw, 0, offset)
                master.send_processdata()
                master.receive_processdata(RECEIVE_US)
                rows.append(struct.unpack("<Hiih", slave.input))
        out["op"] = master.read_state()
        out["rows"] = rows
    finally:
        master.close()
    return out


def link_complete_access(iface: str, url: str) -> dict:
    """Complete access refused or stored wrong; entry by entry; 0x1C32:02 read only."""
    pysoem, master, slave = _open(iface)
    out: dict = {"cycle_time": _abort(pysoem, lambda: slave.sdo_write(0x1C32, 2, bytes(4)))}
    try:
        written = struct.pack("<Bx3I", len(REMAP), *REMAP)
        out["ca_write"] = _abort(pysoem, lambda: slave.sdo_write(0x1A00, 0, written, ca=True))
        out["ca_read"] = _abort(pysoem, lambda: slave.sdo_read(0x1A00, 0, ca=True))
        out["after_ca"] = [slave.sdo_read(0x1A00, s).hex() for s in range(4)]
        _map_entry_by_entry(slave, 0x1A00, REMAP)
        out["entry_by_entry"] = [slave.sdo_read(0x1A00, s).hex() for s in range(4)]
        out["written"] = [bytes([len(REMAP)]).hex()] + [struct.pack("<I", e).hex() for e in REMAP]
    finally:
        master.close()
    return out


def link_quick_stop(iface: str, url: str) -> dict:
    """0x605A, then shutdown, switch on, enable, quick stop, disable voltage by SDO in PRE-OP."""
    pysoem, master, slave = _open(iface)
    try:
        option = struct.unpack("<h", slave.sdo_read(0x605A, 0))[0]
        return {"option": option, "sw": _controlwords_by_sdo(slave, (0x06, 0x07, 0x0F, 0x02, 0x00))}
    finally:
        master.close()


# --------------------------------------------------------------------- tests
def test_no_cst_refuses_cst_and_runs_csp_with_the_torque_offset() -> None:
    out = run_on_link(__file__, "link_no_cst", SIM, ["--clock", "lockstep", "--profile", "no-cst"])
    assert not out["modes"] & 1 << 9 and out["modes"] & 1 << 7  # no CST, CSP
    assert out["cst"] == VALUE_RANGE and out["csp"] == 0
    assert out["cycle_time"] == 0  # writable without cycle-time-ro
    assert out["op"] == 0x08
    sw, torque = [r[0] & 0x6F for r in out["rows"]], [r[3] for r in out["rows"]]
    assert sw[-1] == ENABLED and torque[-3] == 0
    assert torque[-1] == pytest.approx(300, abs=30)  # the loop's output plus the offset


def test_no_complete_access_aborts_0x06010000() -> None:
    out = run_on_link(__file__, "link_complete_access", SIM, ["--profile", "no-complete-access"])
    assert out["ca_write"] == out["ca_read"] == UNSUPPORTED_ACCESS
    assert out["entry_by_entry"] == out["written"]


def test_ca_stored_wrong_reads_back_differently_entry_by_entry_works() -> None:
    args = ["--profile", "ca-stored-wrong,cycle-time-ro"]
    out = run_on_link(__file__, "link_complete_access", SIM, args)
    assert out["cycle_time"] == READ_ONLY  # 0x1C32:02
    assert out["ca_write"] == 0 and out["ca_read"] == 0  # answered OK
    assert out["after_ca"] != out["written"]  # the stored mapping is not the one written
    assert out["entry_by_entry"] == out["written"]


@pytest.mark.parametrize(
    "profile, option, stopped",
    [("quick-stop=2", 2, SWITCH_ON_DISABLED), ("quick-stop=6", 6, QUICK_STOP_ACTIVE)],
)
def test_quick_stop_option_code_decides_the_ending_state(profile, option, stopped) -> None:
    out = run_on_link(__file__, "link_quick_stop", SIM, ["--profile", profile])
    assert out["option"] == option
    assert out["sw"][2] & 0x6F == ENABLED
    mask = 0x4F if stopped == SWITCH_ON_DISABLED else 0x6F
    assert out["sw"][3] & mask == stopped
    assert out["sw"][4] & 0x4F == SWITCH_ON_DISABLED


def test_no_quick_stop_stays_enabled_and_disables_on_disable_voltage() -> None:
    out = run_on_link(__file__, "link_quick_stop", SIM, ["--profile", "no-quick-stop"])
    assert out["sw"][2] & 0x6F == ENABLED
    assert out["sw"][3] & 0x6F == ENABLED  # quick stop ignored
    assert out["sw"][4] & 0x4F == SWITCH_ON_DISABLED


@pytest.mark.parametrize(
    "args, says",
    [
        (["--transport", "canopen", "--profile", "no-cst"], "ethercat only"),
        (["--transport", "ethercat", "--iface", "x", "--profile", "no-cts"], "unknown profile"),
        (["--transport", "ethercat", "--iface", "x", "--profile", "quick-stop=9"], "0..8"),
        (["--transport", "ethercat", "--profile", "quick-stop=1,no-quick-stop"], "contradict"),
    ],
)
def test_profile_usage_errors_are_one_line(args, says, capsys) -> None:
    from servobench.bench.cli import main

    assert main(["serve-sim", *args]) == 1
    err = capsys.readouterr().err
    assert says in err and err.count("\n") == 1
