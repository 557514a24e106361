"""The served Modbus drive against the Modbus specification and peers servobench did not write.

* Golden frames, byte for byte, from MODBUS Application Protocol v1.1b3 (the
  function codes, the exception rules of §7 and the request-processing order
  of §6), Modbus Messaging on TCP/IP Implementation Guide v1.0b (MBAP header,
  unit id 0xFF/0 for a device addressed directly) and Modbus over Serial Line
  v1.02 (unit-id rules, broadcast silence, the CRC of Appendix B), sent raw
  over TCP and over the served RTU line.
* Independent clients against the served drive: pyModbusTCP (TCP) and
  minimalmodbus (RTU), from PyPI; mbpoll (libmodbus) is in test_modbus_mbpoll.py.
"""

from __future__ import annotations

import os
import select
import socket
import struct
import time
from collections.abc import Iterator

import minimalmodbus
import pytest
import serial
from pyModbusTCP.client import ModbusClient

from servobench import __version__
from servobench.bench.testing.served_modbus import host_port, rtu_path, served_modbus
from servobench.sim_backend.device import PowerState, SimulatedDevice
from servobench.sim_backend.servers.modbus.framing import crc16

#: servobench-sim.toml addresses (0-based PDU addresses).
CONTROL, WATCHDOG, COMMAND, STATUS, FAULT, VELOCITY = 0x00, 0x01, 0x10, 0x20, 0x21, 0x24


def served(transport: str, wall_clock: bool = False):
    return served_modbus(transport, wall_clock=wall_clock)


# ------------------------------------------------------------------ raw TCP
class RawTcp:
    """A raw Modbus TCP connection: MBAP frames built here, by the Implementation Guide."""

    def __init__(self, url: str) -> None:
        self.sock = socket.create_connection(host_port(url), timeout=2)
        self.tid = 0

    def ask(self, unit: int, pdu: bytes, protocol: int = 0, timeout_s: float = 2.0) -> bytes | None:
        """Send one request; the response PDU (MBAP checked), or None after ``timeout_s`` of silence."""
        self.tid += 1
        self.sock.sendall(struct.pack(">HHHB", self.tid, protocol, len(pdu) + 1, unit) + pdu)
        self.sock.settimeout(timeout_s)
        try:
            head = self._exactly(7)
        except TimeoutError:
            return None
        tid, proto, length, echoed = struct.unpack(">HHHB", head)
        assert (tid, proto, echoed) == (self.tid, 0, unit)  # transaction and unit echoed
        return self._exactly(length - 1)

    def _exactly(self, n: int) -> bytes:
        data = b""
        while len(data) < n:
            chunk = self.sock.recv(n - len(data))
            if not chunk:
                raise ConnectionError("closed")
            data += chunk
        return data

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def tcp() -> Iterator[tuple[SimulatedDevice, RawTcp]]:
    with served("modbus-tcp") as (device, url):
        raw = RawTcp(url)
        try:
            yield device, raw
        finally:
            raw.close()


@pytest.mark.parametrize(
    ("pdu", "expected"),
    [
        # §7: an undefined function code is exception 01, function code | 0x80
        (bytes([0x41]), bytes([0xC1, 0x01])),
        (bytes([0x64, 0x00]), bytes([0xE4, 0x01])),
        # §6.3 FC03: quantity 0 and 126 are outside 1..125 -> exception 03 (checked before the address)
        (bytes.fromhex("0300210000"), bytes.fromhex("8303")),
        (bytes.fromhex("030021007E"), bytes.fromhex("8303")),
        (bytes.fromhex("0370000001"), bytes.fromhex("8302")),  # no register there: 02
        # the drive has no coils and no discrete inputs: FC01, FC02, FC05, FC15 are not implemented
        (bytes.fromhex("0100000001"), bytes.fromhex("8101")),
        (bytes.fromhex("0200000001"), bytes.fromhex("8201")),
        (bytes.fromhex("050000FF00"), bytes.fromhex("8501")),
        (bytes.fromhex("0F000000010101"), bytes.fromhex("8F01")),
        # §6.6 FC06 to a read-only register (the fault register): address not allowable
        (bytes.fromhex("0600210001"), bytes.fromhex("8602")),
        # §6.12 FC16: byte count that does not match the quantity
        (bytes.fromhex("1000100002030000FF"), bytes.fromhex("9003")),
        # §6.17 FC23: write quantity 0
        (bytes.fromhex("17002000080010000000"), bytes.fromhex("9703")),
        # §6.21 Read Device Identification: unknown read code, unknown individual object
        (bytes.fromhex("2B0E0500"), bytes.fromhex("AB03")),
        (bytes.fromhex("2B0E0405"), bytes.fromhex("AB02")),
        (bytes.fromhex("2B0D0100"), bytes.fromhex("AB01")),  # MEI type 13 (CANopen) not served
    ],
)
def test_tcp_exception_rules(tcp, pdu, expected):
    _, raw = tcp
    assert raw.ask(1, pdu) == expected


def test_tcp_reads_and_writes_answer_as_the_spec_frames_them(tcp):
    device, raw = tcp
    assert raw.ask(1, bytes.fromhex("0300210001")) == bytes.fromhex("03020000")  # fault = 0
    # FC06 echoes the request (§6.6): watchdog register = 500 ms
    assert raw.ask(1, bytes.fromhex("06000101F4")) == bytes.fromhex("06000101F4")
    assert device.watchdog_s == pytest.approx(0.5)
    # FC16 answers address and quantity (§6.12): command = 1.5 N m = 1500000 uN m
    assert raw.ask(1, bytes.fromhex("1000100002040016E360")) == bytes.fromhex("1000100002")
    # FC23 answers byte count and registers (§6.17)
    answer = raw.ask(1, bytes.fromhex("17" "0020" "0008" "0010" "0002" "04" "00000000"))
    assert answer is not None and answer[:2] == bytes([0x17, 16]) and len(answer) == 18


@pytest.mark.parametrize("unit", [0x00, 0xFF])
def test_tcp_units_0_and_ff_address_the_device_itself(tcp, unit):
    _, raw = tcp
    # Implementation Guide v1.0b §4.4.1.2: 0xFF (and 0) for a device addressed by its IP
    assert raw.ask(unit, bytes.fromhex("0300210001")) == bytes.fromhex("03020000")


def test_tcp_other_units_get_the_gateway_exception(tcp):
    _, raw = tcp
    assert raw.ask(7, bytes.fromhex("0300210001")) == bytes.fromhex("830B")


def test_tcp_frame_with_a_foreign_protocol_id_is_dropped(tcp):
    _, raw = tcp
    assert raw.ask(1, bytes.fromhex("0300210001"), protocol=1, timeout_s=0.2) is None


def test_tcp_read_device_identification_basic(tcp):
    _, raw = tcp
    objects = [b"servobench", b"simulated DC servo", __version__.encode()]
    body = b"".join(bytes([i, len(o)]) + o for i, o in enumerate(objects))
    # MEI 0E, code 01, conformity 0x81, more follows 00, next object 00, 3 objects (§6.21)
    assert raw.ask(1, bytes.fromhex("2B0E0100")) == bytes.fromhex("2B0E0181000003") + body
    assert raw.ask(1, bytes.fromhex("2B0E0401")) == bytes.fromhex("2B0E0481000001") + body[
        2 + len(objects[0]) : 4 + len(objects[0]) + len(objects[1])
    ]


# ------------------------------------------------------------------ raw RTU
def test_crc_of_the_serial_line_specification():
    # Modbus over Serial Line v1.02, Appendix B: the CRC of 02 07 is 0x1241 (sent 41 12)
    assert crc16(bytes.fromhex("0207")) == 0x1241
    assert minimalmodbus._calculate_crc(b"\x02\x07") == b"\x41\x12"  # an independent one, table-driven


class RawRtu:
    """The client end of the served RTU line, raw bytes."""

    def __init__(self, path: str) -> None:
        self.port = serial.Serial(path, 115200, timeout=0)

    def ask(self, frame: bytes, quiet_s: float = 0.15) -> bytes:
        """Send ``frame``; every byte that comes back until the line stays quiet ``quiet_s``."""
        self.port.reset_input_buffer()
        self.port.write(frame)
        got = b""
        deadline = time.monotonic() + quiet_s
        while (left := deadline - time.monotonic()) > 0:
            if select.select([self.port.fileno()], [], [], left)[0]:
                got += os.read(self.port.fileno(), 256)
                deadline = time.monotonic() + 0.02  # the frame is whole once the line rests
        return got

    def close(self) -> None:
        self.port.close()


@pytest.fixture
def rtu() -> Iterator[tuple[SimulatedDevice, RawRtu]]:
    with served("modbus-rtu") as (device, url):
        raw = RawRtu(rtu_path(url))
        try:
            yield device, raw
        finally:
            raw.close()


def test_rtu_answers_its_own_unit_with_a_valid_crc(rtu):
    _, raw = rtu
    # read the fault register: 01 03 00 21 00 01 + CRC D4 00 -> 01 03 02 00 00 + CRC B8 44
    assert raw.ask(bytes.fromhex("010300210001D400")) == bytes.fromhex("0103020000B844")
    # an undefined function: exception 01, CRC over "01 C1 01"
    reply = raw.ask(bytes.fromhex("0141") + struct.pack("<H", crc16(bytes.fromhex("0141"))))
    assert reply == bytes.fromhex("01C101") + struct.pack("<H", crc16(bytes.fromhex("01C101")))


@pytest.mark.parametrize("unit", [2, 0xF7])
def test_rtu_is_silent_to_other_units_on_the_line(rtu, unit):
    device, raw = rtu
    body = bytes([unit]) + bytes.fromhex("0300210001")
    assert raw.ask(body + struct.pack("<H", crc16(body))) == b""
    # ... and to its own unit when the CRC is wrong (Serial Line v1.02 §2.4.1: frame discarded)
    assert raw.ask(bytes.fromhex("010300210001D401")) == b""


def test_rtu_broadcast_is_executed_and_never_answered(rtu):
    device, raw = rtu
    write = bytes.fromhex("000600010190")  # unit 0, FC06 watchdog = 400 ms
    assert raw.ask(write + struct.pack("<H", crc16(write))) == b""
    assert device.watchdog_s == pytest.approx(0.4)  # executed
    read = bytes.fromhex("000300210001")  # a broadcast read: not a broadcast function, ignored
    assert raw.ask(read + struct.pack("<H", crc16(read))) == b""


def test_rtu_report_server_id(rtu):
    _, raw = rtu
    request = bytes.fromhex("0111")
    reply = raw.ask(request + struct.pack("<H", crc16(request)))
    assert reply[:2] == bytes.fromhex("0111") and crc16(reply[:-2]) == struct.unpack("<H", reply[-2:])[0]
    data = reply[3:-2]
    assert reply[2] == len(data) and data[:2] == bytes([0x01, 0x00])  # server id 1, not running
    assert b"simulated DC servo" in data


# ---------------------------------------------------- independent clients
def test_pymodbustcp_client_drives_the_served_drive(tmp_path):
    with served("modbus-tcp") as (device, url):
        host, port = host_port(url)
        c = ModbusClient(host=host, port=port, unit_id=1, timeout=2.0, auto_open=True)
        try:
            assert c.read_holding_registers(FAULT, 1) == [0]
            assert c.write_single_register(WATCHDOG, 0)  # watchdog off for this slow client
            assert c.write_single_register(CONTROL, 1)  # enable
            assert device.state is PowerState.ENABLED
            words = [0x000F, 0x4240]  # 1.0 N m = 1000000 uN m, high word first
            v = []
            for _ in range(5):  # FC23: write the command, read status..position
                regs = c.write_read_multiple_registers(COMMAND, words, STATUS, 8)
                assert regs is not None and len(regs) == 8
                v.append(struct.unpack(">i", struct.pack(">HH", regs[4], regs[5]))[0] * 1e-6)
            assert v[0] == 0 and all(b > a for a, b in zip(v[1:], v[2:], strict=False))
            ident = c.read_device_identification()
            assert ident is not None and ident.vendor_name == b"servobench"
            assert ident.product_code == b"simulated DC servo"
            assert c.read_holding_registers(0x0300, 1) is None
            assert c.last_except == 0x02  # illegal data address
            c.unit_id = 7
            assert c.read_holding_registers(FAULT, 1) is None
            assert c.last_except == 0x0B  # gateway target device failed to respond
        finally:
            c.close()


def test_minimalmodbus_client_on_the_served_rtu_line():
    with served("modbus-rtu") as (device, url):
        inst = minimalmodbus.Instrument(rtu_path(url), 1)
        inst.serial.baudrate, inst.serial.timeout = 115200, 0.3
        try:
            assert inst.read_register(FAULT, functioncode=3) == 0
            inst.write_register(WATCHDOG, 0, functioncode=6)
            inst.write_register(CONTROL, 1, functioncode=6)
            inst.write_long(COMMAND, 1_000_000, signed=True)  # FC16, 1.0 N m
            assert inst.read_long(VELOCITY, signed=True) == 0  # sampled before the command acts
            assert inst.read_long(VELOCITY, signed=True) > 0  # a clocking read each time
            strange = minimalmodbus.Instrument(rtu_path(url), 2)
            strange.serial.baudrate, strange.serial.timeout = 115200, 0.2
            with pytest.raises(minimalmodbus.NoResponseError):
                strange.read_register(FAULT)  # another unit on the line: silence
            everybody = minimalmodbus.Instrument(rtu_path(url), 0)
            everybody.serial.baudrate = 115200
            everybody.write_register(CONTROL, 0, functioncode=6)  # broadcast disable, no answer
            assert device.state is PowerState.DISABLED
        finally:
            inst.serial.close()
