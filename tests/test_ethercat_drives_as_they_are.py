"""``ethercat://`` against served slaves that behave as real drives do (issue 29).

The served slave's profiles (``serve-sim --profile``): a read-only 0x1C32:02,
complete access refused or stored wrongly, the quick stop as 0x605A says or
not honoured at all, no cyclic synchronous torque. Each ``link_*`` function
runs in a child process on a private veth link
(:mod:`servobench.bench.testing.ethercat_link`). After each run a raw
broadcast read of the test's own looks at the slave as the master left it:
in INIT or PRE-OP, its SM watchdog disarmed.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile

import pytest

from servobench.bench.testing.ethercat_link import link_unavailable, run_on_link

pytestmark = pytest.mark.slow  # each case starts a namespace, a served slave and a sidbe

PLANT = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"
LOCKSTEP = ["--clock", "lockstep"]
SHORT = ["--no-plots", "--periods", "2", "--period", "2"]


def _link_tests() -> None:
    why = link_unavailable()
    if why is not None:  # a failure to fix (run as root, or allow user namespaces), never a skip
        pytest.fail(f"no private EtherCAT link: {why}")


def brd(iface: str, ado: int, size: int) -> bytes:
    """A broadcast read (BRD) of ``size`` bytes at register ``ado``, in a raw frame of our own: no
    scan, nothing written, so the slave is seen as the master left it."""
    import socket
    import struct

    datagram = struct.pack("<BBHHHH", 7, 0x5A, 0, ado, size, 0) + bytes(size) + b"\0\0"
    frame = b"\xff" * 6 + b"\x01" * 6 + b"\x88\xa4"  # as SOEM sends it; the slave marks it (0x02)
    frame += struct.pack("<H", len(datagram) | 1 << 12) + datagram
    with socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(0x88A4)) as sock:
        sock.bind((iface, 0))
        sock.settimeout(1.0)
        sock.send(frame.ljust(60, b"\0"))
        while True:
            data, addr = sock.recvfrom(1514)
            if data[6] & 0x02 and data[16] == 7 and data[17] == 0x5A:
                return data[26 : 26 + size]


def _slave_after(iface: str) -> dict:
    """AL state (0x0130) and SM watchdog time (0x0420) of the slave, as the master left it."""
    return {
        "al": brd(iface, 0x0130, 1)[0] & 0x0F,
        "wd": int.from_bytes(brd(iface, 0x0420, 2), "little"),
    }


def link_sidbe(iface: str, url: str, extra: str = "") -> dict:
    """A short sidbe (2 periods of 2 s), then the slave as the master left it."""
    with tempfile.TemporaryDirectory() as tmp:
        out = subprocess.run(
            [sys.executable, "-m", "servobench", "sidbe", "--drive", url + extra, "--json",
             "--out", tmp + "/run", *SHORT],
            capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        head = ""
        if out.returncode == 0:
            with open(tmp + "/run/log.csv") as f:
                head = "".join(line for line in f if line.startswith("#"))
    return {"rc": out.returncode, "stdout": out.stdout, "stderr": out.stderr[-3000:], "meta": head,
            "after": _slave_after(iface)}  # fmt: skip


def link_sidbe_fast(iface: str, url: str) -> dict:
    return link_sidbe(iface, url, "&pace=fast")


def link_stop(iface: str, url: str) -> dict:
    """Enable, stream, stop: how the driver stopped the axis, and the state it left it in."""
    from servobench.drivers.registry import open_drive

    out: dict = {}
    with open_drive(url) as drive:
        drive.set_cycle(0.001)
        drive.enable()
        for _ in range(300):
            drive.exchange(0.8)
        drive.stop()
        out["after_stop"] = drive.info().state
        out["remarks"] = list(drive.remarks)
        out["meta"] = drive.log_metadata()
        drive.disable()
        out["after_disable"] = drive.info().state
    out["after"] = _slave_after(iface)
    return out


def link_open(iface: str, url: str) -> dict:
    """Open, enable, stream a little: what the driver made of the slave's quirks."""
    from servobench.drivers.registry import open_drive

    with open_drive(url) as drive:
        for period_s in (0.002, 0.001, 0.002):  # each time back to PRE-OP: a refusal is said once
            drive.set_cycle(period_s)
        drive.enable()
        rows = [drive.exchange(0.8)[0] for _ in range(200)]
        return {
            "meta": drive.log_metadata(),
            "remarks": list(drive.remarks),
            "v": rows[-1].velocity,
        }


def link_hold_only(iface: str, url: str) -> dict:
    """A drive without CST: enabled, it holds; a command outside a hold is refused in one line;
    under the hold the excitation is the torque offset and 0x6077 the total."""
    from servobench.drivers.registry import open_drive
    from servobench.errors import UsageError

    out: dict = {}
    with open_drive(url) as drive:
        out["hold_only"], out["meta"] = drive.hold_only, drive.log_metadata()
        drive.set_cycle(0.001)
        drive.enable()
        x0 = drive.exchange(0.0)[0].position
        try:
            drive.exchange(0.5)
        except UsageError as err:
            out["refused"] = str(err)
        drive.hold_position(x0)
        rows = [drive.exchange(0.8 if (k // 100) % 2 else -0.8)[0] for k in range(600)]
        out["x0"], out["x"] = x0, [r.position for r in rows]
        out["applied"] = [r.applied for r in rows]
    out["after"] = _slave_after(iface)
    return out


# --------------------------------------------------------------------- tests
def _model(out: dict) -> dict:
    assert out["rc"] == 0, out["stderr"]
    assert "Traceback" not in out["stderr"]
    return json.loads(out["stdout"])


def _left_safe(out: dict) -> None:
    assert out["after"]["al"] in (0x01, 0x02), out["after"]  # INIT or PRE-OP
    assert out["after"]["wd"] == 0  # the SM watchdog disarmed at close


@pytest.mark.parametrize("profile", ["cycle-time-ro", "no-complete-access", "ca-stored-wrong",
                                     "quick-stop=2", "quick-stop=6", "no-quick-stop"])  # fmt: skip
def test_sidbe_yields_a_model_on_a_drive_as_it_is(profile) -> None:
    _link_tests()
    out = run_on_link(__file__, "link_sidbe_fast", PLANT, [*LOCKSTEP, "--profile", profile])
    model = _model(out)
    assert model["pole"] == pytest.approx(-10.0, rel=0.02), out["stderr"]
    assert model["dc_gain"] == pytest.approx(1.0, rel=0.02)
    assert "# status = complete" in out["meta"]
    if profile == "cycle-time-ro":  # 0x1C32:02 holds 1 ms already: read, not written, no remark
        assert "# remarks" not in out["meta"]
    if (
        profile == "no-quick-stop"
    ):  # the last stop: by disable voltage, the log complete all the same
        assert model["remarks"][0].startswith("stopped by disable voltage"), model.get("remarks")
    else:
        assert "remarks" not in model
    _left_safe(out)


def test_a_read_only_cycle_time_is_a_remark_said_once() -> None:
    _link_tests()
    out = run_on_link(__file__, "link_open", PLANT, [*LOCKSTEP, "--profile", "cycle-time-ro"])
    assert out["v"] > 0.1
    assert len(out["remarks"]) == 1 and out["remarks"][0].startswith("SM2 cycle time 0x1C32:2 = ")
    assert "0x06010002" in out["remarks"][0] and "left at" in out["remarks"][0]
    assert out["meta"]["remarks"] == out["remarks"][0]


@pytest.mark.parametrize(("profile", "says"), [
    ("no-complete-access", "refused: mapped entry by entry"),
    ("ca-stored-wrong", "stored wrongly (0x1C12/0x1600 read back nothing assigned"),
])  # fmt: skip
def test_the_mapping_holds_or_falls_back_entry_by_entry(profile, says) -> None:
    _link_tests()
    out = run_on_link(__file__, "link_open", PLANT, [*LOCKSTEP, "--profile", profile])
    assert out["meta"]["complete_access"].startswith(says), out["meta"]["complete_access"]
    assert out["meta"]["drive_clock"].startswith("0x10F8")  # the time stamp mapped all the same
    assert out["v"] > 0.1 and out["remarks"] == []


@pytest.mark.parametrize(("profile", "state", "remark"), [
    ("quick-stop=0", "SWITCH ON DISABLED", False),
    ("quick-stop=2", "SWITCH ON DISABLED", False),
    ("quick-stop=6", "QUICK STOP ACTIVE", False),
    ("no-quick-stop", "SWITCH ON DISABLED", True),
])  # fmt: skip
def test_the_quick_stop_follows_0x605A_and_disable_voltage_stops_the_rest(
    profile, state, remark
) -> None:
    _link_tests()
    out = run_on_link(__file__, "link_stop", PLANT, [*LOCKSTEP, "--profile", profile])
    assert out["after_stop"] == state
    assert out["after_disable"] == "SWITCH ON DISABLED"
    if remark:
        assert out["remarks"] == [out["remarks"][0]]
        assert out["remarks"][0].startswith(
            "stopped by disable voltage: the drive did not honour the quick stop"
        )
    else:
        assert out["remarks"] == []
    _left_safe(out)


def test_a_drive_without_cst_is_commanded_under_its_own_hold() -> None:
    _link_tests()
    out = run_on_link(__file__, "link_hold_only", PLANT, [*LOCKSTEP, "--profile", "no-cst"])
    assert out["hold_only"]
    assert out["meta"]["command"].startswith(
        "torque offset 0x60B2 under the drive's own cyclic synchronous"
    )
    assert "bit 9 clear" in out["meta"]["command"]
    assert "hold_position" in out["refused"] and "\n" not in out["refused"]
    assert max(abs(x - out["x0"]) for x in out["x"]) < 0.05  # held
    assert (
        max(abs(a) for a in out["applied"][100:]) > 0.85
    )  # 0x6077: the loop's torque and the offset
    _left_safe(out)


def test_mode_csp_commands_any_drive_under_its_own_hold() -> None:
    _link_tests()
    out = run_on_link(__file__, "link_hold_only", PLANT + "", [*LOCKSTEP])  # the default slave
    assert out["hold_only"] is False  # without mode=csp: CST
    out = run_on_link(__file__, "link_hold_only_csp", PLANT, [*LOCKSTEP])
    assert out["hold_only"] and "(mode=csp)" in out["meta"]["command"]


def link_hold_only_csp(iface: str, url: str) -> dict:
    return link_hold_only(iface, url + "&mode=csp")


def test_no_cst_with_mode_cst_is_one_line_and_json() -> None:
    _link_tests()
    out = run_on_link(__file__, "link_sidbe_mode_cst", PLANT, [*LOCKSTEP, "--profile", "no-cst"])
    assert out["rc"] == 1 and "Traceback" not in out["stderr"]
    lines = out["stderr"].strip().splitlines()
    assert (
        len(lines) == 1 and lines[0].startswith("servobench: error:") and "bit 9 clear" in lines[0]
    )
    assert "mode=cst" in json.loads(out["stdout"])["error"]
    _left_safe(out)


def link_sidbe_mode_cst(iface: str, url: str) -> dict:
    return link_sidbe(iface, url, "&mode=cst")


def test_pysoem_errors_are_one_line_naming_slave_object_and_abort() -> None:
    import pysoem

    from servobench.drivers.ethercat.master import EthercatMaster
    from servobench.drivers.ethercat.options import EthercatOptions
    from servobench.drivers.url import parse_drive_url
    from servobench.errors import DriveConfigError, DriveTimeoutError

    master = EthercatMaster(EthercatOptions.from_url(parse_drive_url("ethercat://eth9?slave=2")))
    refused = pysoem.SdoError(2, 0x1C00, 0, 0x06010000, "Unsupported access to an object")
    with pytest.raises(DriveConfigError) as err, master.translated("PDO mapping (SOEM config_map)"):
        raise pysoem.ConfigMapError([refused])
    assert str(err.value) == ("EtherCAT slave 2 on eth9: PDO mapping (SOEM config_map): SDO 0x1C00:0 aborted "
                              "0x06010000 (Unsupported access to an object)")  # fmt: skip
    assert err.value.abort_code == 0x06010000
    with pytest.raises(DriveConfigError, match=r"SDO write 0x1C32:2: mailbox answer not the one asked for"), \
            master.translated("SDO write 0x1C32:2"):  # fmt: skip
        raise pysoem.PacketError(2, 1)
    with (
        pytest.raises(DriveTimeoutError, match="no answer"),
        master.translated("SDO read 0x6041:0"),
    ):
        raise pysoem.WkcError()
    read_only = pysoem.SdoError(2, 0x1C32, 2, 0x06010002, "")
    with pytest.raises(DriveConfigError, match=r"0x06010002 \(Attempt to write a read only object\)"), \
            master.translated("SDO write 0x1C32:2"):  # fmt: skip
        raise read_only


# --------------------------------------------------------------------- CANopen
def test_canopen_quick_stop_active_counts_as_stopped_and_mode_csp_holds() -> None:
    from servobench.bench.testing.served_canopen import served, station
    from servobench.errors import UsageError

    with served() as (_device, url):
        with station(url) as node:
            node.sdo[0x605A].raw = 2  # says SWITCH ON DISABLED; the served drive stays in QSA
        with open_drive_canopen(url) as drive:
            drive.enable()
            for _ in range(100):
                drive.exchange(0.8)
            drive.stop()
            assert drive.info().state == "QUICK STOP ACTIVE" and drive.remarks == []
            assert (
                drive.log_metadata()["quick_stop_option"]
                == "0x605A = 2: ends in SWITCH ON DISABLED"
            )
        with open_drive_canopen(url + "&mode=csp") as drive:
            assert drive.hold_only and "(mode=csp)" in drive.log_metadata()["command"]
            drive.enable()
            x0 = drive.exchange(0.0)[0].position
            with pytest.raises(UsageError, match="hold_position"):
                drive.exchange(0.5)
            drive.hold_position(x0)
            rows = [drive.exchange(0.8 if (k // 100) % 2 else -0.8)[0] for k in range(400)]
            assert max(abs(r.position - x0) for r in rows) < 0.05
            assert max(abs(r.applied) for r in rows[100:]) > 0.85


def open_drive_canopen(url: str):
    from servobench.bench.testing.served import PATIENT_KEYS
    from servobench.drivers.registry import open_drive

    # patient: a loaded suite may hold the served node past the 100 ms default wait for its TPDO
    return open_drive(url + "&pace=fast" + PATIENT_KEYS["canopen"])


def test_canopen_drive_without_cst_is_commanded_under_its_own_hold(tmp_path) -> None:
    from importlib.resources import files

    from servobench.bench.testing.served_canopen import served

    eds = (files("servobench.drivers") / "data" / "cia402.eds").read_text()
    no_cst = tmp_path / "no-cst.eds"  # 0x6502: profile torque and CSP, no CST (bit 9)
    no_cst.write_text(eds.replace("DefaultValue=0x00000288", "DefaultValue=0x00000088", 1))
    with served(eds=str(no_cst)) as (_device, url), open_drive_canopen(url) as drive:
        assert drive.hold_only and "bit 9 clear" in drive.log_metadata()["command"]
        drive.enable()
        drive.hold_position(drive.exchange(0.0)[0].position)
        applied = [drive.exchange(0.8)[0].applied for _ in range(300)]
        assert min(applied[100:]) < 0.5  # 0x6077: the loop pushes back against the offset
