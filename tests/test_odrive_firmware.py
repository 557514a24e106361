"""ODrive: leaving the drive as firmware 0.5.x expects (issue 10 §2).

The served drive follows ODrive's firmware source at fw-v0.5.1 and fw-v0.5.6
(github.com/odriverobotics/ODrive): ``Firmware/communication/ascii_protocol.cpp``
for the line handling and its rejection texts, ``Firmware/MotorControl/axis.cpp``
(``watchdog_check``) for an axis watchdog checked in every state whose error
latches. The expectations below are read from those files, not from
servobench's dialect.
"""

from __future__ import annotations

import time
import warnings

import pytest
import serial

from servobench.bench.testing.served import ServedSim
from servobench.drivers.registry import open_drive
from servobench.drivers.serial.dialect import load_dialect
from servobench.errors import DriveConfigError, DriveWarning
from servobench.sim_backend.device import PowerState, SimulatedDevice
from servobench.sim_backend.physics.plant import PlantParams
from servobench.sim_backend.servers.serial.serve_serial import AsciiDriveServer

SIM = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"
WATCHDOG_TIMER_EXPIRED = 0x800
FIRMWARE = ["0.5.1", "0.5.6"]


def drive_at(version: tuple[int, ...]) -> tuple[SimulatedDevice, AsciiDriveServer]:
    device = SimulatedDevice(PlantParams())
    return device, AsciiDriveServer(device, load_dialect("odrive"), firmware=version)


# ------------------------------------------------------------- the firmware's lines
@pytest.mark.parametrize(
    ("line", "v051", "v056"),
    [
        # empty line: fw-v0.5.1 processes it only "else if (cmd[0] != 0)"; fw-v0.5.6 "default:"
        (b"", b"", b"unknown command\r\n"),
        (b"x 0", b"unknown command\r\n", b"unknown command\r\n"),
        # sscanf("c %u %f") < 2, ("f %u") < 1, ("r %255s") < 1
        (b"c 0", b"invalid command format\r\n", b"invalid command format\r\n"),
        (b"f", b"invalid command format\r\n", b"invalid command format\r\n"),
        (b"r", b"invalid command format\r\n", b"invalid command format\r\n"),
        (b"f 3", b"invalid motor 3\r\n", b"invalid motor 3\r\n"),
        # get_child() finds no property
        (b"r axis0.nonsense", b"invalid property\r\n", b"invalid property\r\n"),
        (b"w axis0.nonsense 1", b"invalid property\r\n", b"invalid property\r\n"),
        # a read-only property: set_string fails
        (b"w axis0.current_state 8", b"not implemented\r\n", b"not implemented\r\n"),
        # fibre to_string: %u, %f, '0'/'1'
        (b"r fw_version_minor", b"5\r\n", b"5\r\n"),
        (b"r axis0.config.enable_watchdog", b"0\r\n", b"0\r\n"),
        (b"r vbus_voltage", b"24.000000\r\n", b"24.000000\r\n"),
    ],
)
def test_lines_answered_as_the_firmware_answers_them(line, v051, v056):
    assert drive_at((0, 5, 1))[1].handle(line) == v051
    assert drive_at((0, 5, 6))[1].handle(line) == v056


@pytest.mark.parametrize("version", [(0, 5, 1), (0, 5, 6)])
def test_the_version_is_read_from_its_properties(version):
    _, server = drive_at(version)
    parts = [server.handle(f"r fw_version_{p}".encode()) for p in ("major", "minor", "revision")]
    assert tuple(int(p) for p in parts) == version


@pytest.mark.parametrize("version", [(0, 5, 1), (0, 5, 6)])
def test_watchdog_checked_idle_and_latching(version):
    device, server = drive_at(version)
    server.handle(b"w axis0.config.watchdog_timeout 0.05")
    server.handle(b"u 0")
    server.handle(b"w axis0.config.enable_watchdog 1")
    server.handle(b"r axis0.error")  # reads do not feed the watchdog
    time.sleep(0.08)
    assert device.state is PowerState.DISABLED and device.check_watchdog()  # idle, and it trips
    assert server.handle(b"r axis0.error") == b"2048\r\n"
    assert server.handle(b"r axis0.current_state") == b"1\r\n"
    server.handle(b"w axis0.config.enable_watchdog 0")
    assert server.handle(b"r axis0.error") == b"2048\r\n"  # latched until cleared


def test_sc_exists_from_0_5_2_and_0_5_1_clears_by_property():
    for version, cleared_by_sc in (((0, 5, 1), False), ((0, 5, 2), True), ((0, 5, 6), True)):
        device, server = drive_at(version)
        device.set_watchdog(0.01)
        time.sleep(0.03)
        assert device.check_watchdog()
        assert server.handle(b"sc") == b""  # 0.5.1: 's' + 'c' is no command, and says nothing
        assert (server.handle(b"r axis0.error") == b"0\r\n") is cleared_by_sc, version
        server.handle(b"w axis0.error 0")
        assert server.handle(b"r axis0.error") == b"0\r\n"
        assert device.state is PowerState.DISABLED


def test_exclamation_mark_ends_a_line_as_newline_and_return_do():
    with ServedSim("serial", SIM) as served:
        port = serial.Serial(served.url.split("://")[1].split("?")[0], 115200, timeout=1)
        try:
            port.write(b"r fw_version_major!r fw_version_minor\rr fw_version_revision\n")
            assert [port.readline() for _ in range(3)] == [b"0\r\n", b"5\r\n", b"6\r\n"]
        finally:
            port.close()


def test_unknown_firmware_is_refused():
    with pytest.raises(DriveConfigError, match="0.6.0 is not modelled"):
        drive_at((0, 6, 0))


# ------------------------------------------------------------ sessions back to back
def session(url: str, n: int = 40) -> None:
    with open_drive(url + "&watchdog=0.2") as drive:
        drive.set_cycle(0.002)
        drive.enable()
        for k in range(n):
            drive.exchange(1.0 if k < n // 2 else -1.0)


@pytest.mark.parametrize("firmware", FIRMWARE)
def test_two_sessions_back_to_back_with_the_drive_idle_between(firmware):
    with ServedSim("serial", SIM, ["--firmware", firmware]) as served, warnings.catch_warnings():
        warnings.simplefilter("error", DriveWarning)  # nothing to clear, nothing to say
        session(served.url)
        time.sleep(0.6)  # idle, three watchdog periods: a watchdog left armed would trip
        session(served.url)
        with open_drive(served.url) as drive:
            assert drive.firmware_version == tuple(int(p) for p in firmware.split("."))
            assert drive.fault_code() == 0
            assert drive.info().firmware == firmware


@pytest.mark.parametrize("firmware", FIRMWARE)
def test_a_watchdog_error_an_earlier_host_left_is_cleared_and_said(firmware):
    with ServedSim("serial", SIM, ["--firmware", firmware]) as served:
        path = served.url.split("://")[1].split("?")[0]
        with serial.Serial(path, 115200, timeout=0.2) as old_host:  # arms it, then goes away
            for line in (b"w axis0.config.watchdog_timeout 0.1", b"u 0",
                         b"w axis0.config.enable_watchdog 1"):  # fmt: skip
                old_host.write(line + b"\n")
            old_host.flush()
        time.sleep(1.5)  # watchdog 0.1 s, plus a margin for a served drive late under load
        drive = open_drive(served.url)
        with pytest.warns(DriveWarning, match=r"0x00000800 \(WATCHDOG_TIMER_EXPIRED\).*cleared"):
            drive.open()
        with drive:
            assert drive.fault_code() == 0
            assert drive.log_metadata()["cleared_at_open"].startswith("0x00000800")
            drive.enable()
            drive.exchange(0.5)
        time.sleep(0.4)  # disarmed on close: idle, it stays clean
        with open_drive(served.url) as again:
            assert again.fault_code() == 0


def run_on_a_fresh_drive(keys: str) -> tuple[object, list]:
    with ServedSim("serial", SIM, clock="lockstep") as served, open_drive(served.url + keys) as drive:
        drive.set_cycle(0.002)
        drive.enable()
        return drive, [drive.exchange(1.5)[0] for _ in range(60)]


def test_units_si_converts_turns_and_says_so():
    turn, turn_rows = run_on_a_fresh_drive("")
    rad, rad_rows = run_on_a_fresh_drive("&units=si")
    assert dict(turn.units) == {"u": "N m", "v": "turn/s", "x": "turn"}
    assert dict(rad.units) == {"u": "N m", "v": "rad/s", "x": "rad"}
    meta = rad.log_metadata()
    assert meta["unit_v"] == "rad/s" and meta["unit_x"] == "rad"
    assert meta["unit_conversion"] == (
        "by the host (units=si): x turn -> rad (* 6.28318531), v turn/s -> rad/s (* 6.28318531)"
    )
    assert "unit_conversion" not in turn.log_metadata()
    two_pi = 2 * 3.141592653589793
    for a, b in zip(turn_rows, rad_rows, strict=True):  # the same plant, the same commands
        assert b.position == pytest.approx(two_pi * a.position, abs=1e-9)
        assert b.velocity == pytest.approx(two_pi * a.velocity, abs=1e-9)
    assert turn_rows[-1].velocity > 0.5


def test_units_must_be_drive_or_si():
    with pytest.raises(DriveConfigError, match="units must be 'drive' or 'si', got 'imperial'"):
        open_drive("serial:///dev/ttyACM7?units=imperial")
