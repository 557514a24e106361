"""The drive side of the serial dialect: request handling and the pty wire, in-process."""

from __future__ import annotations

import threading
import time

import pytest
import serial

from servobench.drivers.serial.ascii_line import encode_line, xor_checksum
from servobench.drivers.serial.dialect import load_dialect
from servobench.errors import DriveConfigError
from servobench.sim_backend.device import WATCHDOG_FAULT, PowerState, SimulatedDevice
from servobench.sim_backend.physics.plant import PlantParams
from servobench.sim_backend.servers.serial.serve_serial import (
    AsciiDriveServer,
    PtyPort,
    UartClock,
    parse_faults,
    pump,
)


@pytest.fixture
def device():
    return SimulatedDevice(PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4))


@pytest.fixture
def server(device):
    return AsciiDriveServer(device, load_dialect("odrive"))


def test_torque_latches_and_feedback_clocks(server, device):
    assert server.handle(b"w axis0.requested_state 8") == b""
    assert device.state is PowerState.ENABLED
    assert server.handle(b"c 0 2.0") == b""
    assert device._k == 0  # the command only latches
    assert server.handle(b"f 0") == b"0.000000 0.000000\r\n"  # sampled before u acts
    assert device._k == 1
    x, v = (float(s) for s in server.handle(b"f 0").split())
    assert v > 0 and x > 0


def test_property_reads_do_not_clock(server, device):
    assert server.handle(b"r axis0.current_state") == b"1\r\n"
    assert server.handle(b"r axis0.encoder.pos_estimate") == b"0.000000\r\n"
    assert server.handle(b"r vbus_voltage") == b"24.000000\r\n"
    assert device._k == 0


def test_checksum_answered_only_when_asked(server):
    assert server.handle(b"r axis0.error") == b"0\r\n"
    reply = server.handle(b"r axis0.error*%d" % xor_checksum("r axis0.error"))
    assert reply == b"0*48\r\n"  # '0' is 0x30 = 48
    assert server.handle(b"r axis0.error*1") == b""  # wrong checksum: ignored


def test_rejections(server):
    assert server.handle(b"x 0") == b"unknown command\r\n"
    assert server.handle(b"f 1") == b"invalid motor 1\r\n"
    assert server.handle(b"w axis0.config.servobench_cycle -1") == b"invalid command format\r\n"
    # an empty line: fw-v0.5.6 ascii_protocol.cpp answers it (switch default), fw-v0.5.1 does not
    assert server.handle(b"") == b"unknown command\r\n"
    old = AsciiDriveServer(SimulatedDevice(PlantParams()), load_dialect("odrive"), firmware=(0, 5, 1))
    assert old.handle(b"") == b""


def test_watchdog_fault_is_reported_as_the_dialect_flag(server, device):
    server.handle(b"w axis0.config.watchdog_timeout 0.01")
    server.handle(b"u 0")
    server.handle(b"w axis0.config.enable_watchdog 1")
    assert device.watchdog_s == 0.01
    assert server.handle(b"r axis0.config.watchdog_timeout") == b"0.010000\r\n"
    server.handle(b"w axis0.requested_state 8")
    time.sleep(0.03)
    assert device.check_watchdog()
    assert device.fault_code == WATCHDOG_FAULT
    assert server.handle(b"r axis0.error") == b"2048\r\n"
    assert server.handle(b"r axis0.current_state") == b"1\r\n"
    server.handle(b"w axis0.requested_state 8")  # refused while in fault
    assert device.state is PowerState.FAULT
    server.handle(b"sc")
    assert server.handle(b"r axis0.error") == b"0\r\n"


def test_set_cycle_extension_and_info(server, device):
    server.handle(b"w axis0.config.servobench_cycle 0.002")
    assert device.cycle_s == 0.002
    assert server.handle(b"r axis0.config.servobench_cycle") == b"0.002000\r\n"
    lines = server.handle(b"i").decode().splitlines()
    assert [line.split(":")[0] for line in lines] == [
        "Hardware version",
        "Firmware version",
        "Serial number",
    ]


def test_injected_faults(device):
    srv = AsciiDriveServer(
        device, load_dialect("odrive"), parse_faults("garble@1;truncate@2;silence@3;fault@4")
    )
    garbled = srv.handle(b"f 0")
    assert garbled.endswith(b"\r\n") and garbled != b"0.000000 0.000000\r\n"
    assert srv.handle(b"f 0") == b"0.000000\r\n"
    assert srv.handle(b"f 0") == b""
    srv.handle(b"f 0")
    assert srv.handle(b"r axis0.error") == b"64\r\n"  # MOTOR_FAILED


@pytest.mark.parametrize("spec", ["garble", "garble@0", "boom@3", "garble@x"])
def test_bad_fault_specs(spec):
    with pytest.raises(DriveConfigError, match="KIND@N"):
        parse_faults(spec)


def test_uart_clock_books_each_direction():
    clock = UartClock(115200)
    assert clock.char_s == pytest.approx(10 / 115200)
    assert clock.receive(10, 1.0) == 1.0
    assert clock.receive(5, 1.0) == pytest.approx(1.0 + 10 * clock.char_s)  # queued behind
    assert clock.transmit(20, 1.0) == pytest.approx(1.0 + 20 * clock.char_s)  # full duplex
    with pytest.raises(DriveConfigError):
        UartClock(0)


def test_pty_wire_paces_replies_at_the_baud_rate(device):
    """Over a real pty with pyserial: a reply arrives no sooner than its bytes take at 9600 baud."""
    stop = threading.Event()
    srv = AsciiDriveServer(device, load_dialect("odrive"))
    with PtyPort() as port:
        t = threading.Thread(target=pump, args=(port.master, srv, UartClock(9600), stop))
        t.start()
        try:
            with serial.Serial(port.path, 9600, timeout=2) as ser:
                request = encode_line("r vbus_voltage", b"\n", checksum=False)
                t0 = time.monotonic()
                ser.write(request)
                reply = ser.read_until(b"\n")
                elapsed = time.monotonic() - t0
        finally:
            stop.set()
            t.join(5)
    assert reply == b"24.000000\r\n"
    wire_s = (len(request) + len(reply)) * 10 / 9600
    assert wire_s <= elapsed < wire_s + 0.05
    assert not t.is_alive()
