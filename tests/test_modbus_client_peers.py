"""servobench's Modbus client against a server it did not write, and its honest messages.

* uModbus (PyPI) as the TCP and the RTU server of a drive laid out as
  ``servobench-sim.toml`` says (RTU over a pseudo-terminal: uModbus frames
  by pyserial's inter-byte time-out and checks the CRC itself). uModbus
  implements FC01-06, FC15, FC16 and not FC23, so it answers FC23 with
  exception 1 (illegal function): a map with ``fc23 = "auto"`` falls back to
  write-then-read, and the cycles still match the plant.
* A wrong unit id, no answer and a gateway exception each say what happened.
* ``feed = "any_request"`` over TCP warns, and the warning is true: a second
  client's polling keeps the drive's watchdog from tripping after the host stops.
"""

from __future__ import annotations

import contextlib
import os
import select
import struct
import threading
import time
import tty
from pathlib import Path
from socketserver import TCPServer

import numpy as np
import pytest
from pyModbusTCP.client import ModbusClient
from umodbus import conf
from umodbus.server.serial import get_server as get_rtu_server
from umodbus.server.serial.rtu import RTUServer
from umodbus.server.tcp import RequestHandler, get_server

from servobench.bench.testing.served_modbus import host_port, rtu_path, served_modbus
from servobench.drivers.modbus.regmap import resolve_map
from servobench.drivers.registry import open_drive
from servobench.errors import DriveConfigError, DriveTimeoutError, DriveWarning
from servobench.sim_backend.device import PowerState, SimulatedDevice
from servobench.sim_backend.physics.plant import PlantParams, simulate

PARAMS = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)
SIM_MAP = Path(resolve_map("servobench-sim")).read_text()
RTU_BAUD = 115200


class UmodbusDrive:
    """The servobench-sim register layout on a uModbus server, a device behind it.

    uModbus calls a route once per register address, in address order, so a
    32-bit value is applied when its second word arrives, and a read of the
    feedback block clocks the device at the velocity's first word. TCP by
    default; with ``rtu=True`` uModbus's RTU server on the master side of a
    pseudo-terminal whose other side (:attr:`path`) the host opens.
    """

    def __init__(self, rtu: bool = False) -> None:
        conf.SIGNED_VALUES = False
        self.device = SimulatedDevice(PARAMS)
        self.words = {a: 0 for a in (0x00, 0x01, 0x02, 0x03, 0x10, 0x11)}
        self.sample = self.device.sample()
        if rtu:
            master, slave = os.openpty()
            tty.setraw(slave)
            self.path = os.ttyname(slave)
            self._fds = (master, slave)
            self.app = get_rtu_server(RTUServer, PtyMasterPort(master, RTU_BAUD))
        else:
            TCPServer.allow_reuse_address = True
            self.app = get_server(TCPServer, ("127.0.0.1", 0), RequestHandler)
        holding = list(range(0x00, 0x04)) + [0x10, 0x11] + list(range(0x20, 0x28))
        self.app.route(slave_ids=[1], function_codes=[3], addresses=holding)(self.read)
        self.app.route(slave_ids=[1], function_codes=[6, 16], addresses=holding)(self.write)
        self.rtu = rtu
        self.thread = threading.Thread(target=self.app.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)

    @property
    def port(self) -> int:
        return self.app.server_address[1]

    def read(self, slave_id: int, function_code: int, address: int) -> int:
        if address < 0x20:
            return self.words[address]
        if address == 0x24:  # the velocity's first word: one lock-step cycle
            self.sample = self.device.step()
        elif address < 0x24:
            self.sample = self.device.sample()
        s = self.sample
        status = {PowerState.ENABLED: 1, PowerState.QUICK_STOP: 2, PowerState.FAULT: 8}
        t_us = round(s.t_s * 1e6) & 0xFFFFFFFF
        vel = struct.unpack(">HH", struct.pack(">i", round(s.velocity * 1e6)))
        pos = struct.unpack(">HH", struct.pack(">i", round(s.position * 1e6)))
        return {
            0x20: status.get(s.state, 0), 0x21: s.fault_code, 0x22: t_us >> 16,
            0x23: t_us & 0xFFFF, 0x24: vel[0], 0x25: vel[1], 0x26: pos[1], 0x27: pos[0],
        }[address]  # fmt: skip

    def write(self, slave_id: int, function_code: int, address: int, value: int) -> None:
        self.words[address] = value
        d = self.device
        if address == 0x00:
            {1: d.enable, 0: d.disable, 2: d.quick_stop, 0x80: d.reset_fault}[value]()
        elif address == 0x01:
            d.set_watchdog(value / 1000 or None)
        elif address == 0x03:
            d.set_cycle(((self.words[0x02] << 16) | value) * 1e-9)
        elif address == 0x11:
            raw = struct.unpack(">i", struct.pack(">HH", self.words[0x10], value))[0]
            d.set_command(raw * 1e-6)

    def __enter__(self) -> UmodbusDrive:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.rtu:
            self.app.shutdown()
            self.thread.join(timeout=2)
            for fd in self._fds:
                os.close(fd)
        else:
            self.app.shutdown()
            self.app.server_close()


class PtyMasterPort:
    """The master side of a pseudo-terminal as the pyserial port uModbus's RTU server reads.

    What pyserial's ``read(size)`` does: wait up to ``timeout`` for the first
    byte, then return once ``inter_byte_timeout`` passes without another (the
    RTU frame gap by which uModbus frames), or ``size`` bytes arrived.
    """

    def __init__(self, fd: int, baudrate: int) -> None:
        self.fd, self.baudrate = fd, baudrate
        self.timeout: float | None = None
        self.inter_byte_timeout: float | None = None

    def read(self, size: int) -> bytes:
        data = b""
        wait = self.timeout
        while len(data) < size:
            if not select.select([self.fd], [], [], wait)[0]:
                break
            data += os.read(self.fd, size - len(data))
            wait = self.inter_byte_timeout
        return data

    def write(self, data: bytes) -> int:
        return os.write(self.fd, data)


@pytest.fixture
def auto_map(tmp_path: Path) -> str:
    path = tmp_path / "auto.toml"
    path.write_text(SIM_MAP.replace("fc23 = true", 'fc23 = "auto"'))
    return str(path)


@pytest.mark.parametrize("rtu", [False, True], ids=["tcp", "rtu"])
def test_fc23_auto_falls_back_to_write_then_read_on_a_drive_without_fc23(auto_map, rtu):
    u = np.where((np.arange(120) // 30) % 2 == 0, 1.5, -1.5)
    with UmodbusDrive(rtu=rtu) as peer:
        # timeout=2: uModbus answers from a thread of this process, late on a loaded machine
        url = (
            f"modbus+rtu://{peer.path}?baud={RTU_BAUD}&unit=1&map={auto_map}&watchdog=0.5&timeout=2" if rtu
            else f"modbus+tcp://127.0.0.1:{peer.port}?unit=1&map={auto_map}&watchdog=0.5&timeout=2"
        )  # fmt: skip
        # over TCP the map's any-request feed warns; an RTU line has one master
        warns = contextlib.nullcontext() if rtu else pytest.warns(DriveWarning, match="another Modbus client")
        with warns, open_drive(url) as drive:
            assert drive.fc23 is True  # tried first
            drive.set_cycle(0.002)
            assert peer.device.cycle_s == pytest.approx(0.002)
            drive.enable()
            rows = [drive.exchange(float(uk))[0] for uk in u]
            assert drive.fc23 is False  # exception 1 from uModbus: write, then read
            assert drive.log_metadata()["fc23"] == "no (the drive answered exception 1)"
        assert peer.device.state is PowerState.DISABLED
    v_ref, x_ref = simulate(u, 500.0, PARAMS)
    np.testing.assert_allclose([r.velocity for r in rows], v_ref, rtol=0, atol=1e-6)
    np.testing.assert_allclose([r.position for r in rows], x_ref, rtol=0, atol=1e-6)
    np.testing.assert_allclose([r.t_s for r in rows], np.arange(len(u)) * 0.002, atol=1e-6)


def test_fc23_true_on_a_drive_without_it_says_so():
    with UmodbusDrive() as peer:
        url = f"modbus+tcp://127.0.0.1:{peer.port}?unit=1&map=servobench-sim"
        with pytest.warns(DriveWarning), open_drive(url) as drive:
            drive.enable()
            with pytest.raises(DriveConfigError, match=r"exception 1 \(illegal function\).*fc23"):
                drive.exchange(0.0)


def test_wrong_unit_ids_say_what_happened():
    with served_modbus("modbus-tcp") as (_, url):
        with pytest.raises(DriveTimeoutError) as err:
            open_drive(url.replace("unit=1", "unit=7")).open()
        text = str(err.value)
        assert "exception 11" in text and "unit 7" in text and "did not respond" in text
        assert "fault" not in text.replace("read fault", "")  # not a drive fault
    with served_modbus("modbus-rtu") as (_, url):
        with pytest.raises(DriveTimeoutError) as err:
            open_drive(url.replace("unit=1", "unit=2") + "&timeout=0.1").open()
        text = str(err.value)
        assert f"no answer from unit 2 at {rtu_path(url)}" in text
        assert "no such unit on the line" in text and "baud 115200" in text


def test_any_request_feed_warns_over_tcp_only_and_a_second_client_does_keep_it_alive():
    with served_modbus("modbus-tcp") as (device, url):
        with pytest.warns(DriveWarning, match="another Modbus client polling this drive"):
            drive = open_drive(url + "&watchdog=0.5")  # ten polls of the other client
            drive.open()
        host, port = host_port(url)
        other = ModbusClient(host=host, port=port, unit_id=1, auto_open=True)
        try:
            drive.enable()
            drive.exchange(0.5)
            deadline = time.monotonic() + 2.0  # four watchdog periods without this host
            while time.monotonic() < deadline:
                assert other.read_holding_registers(0x21, 1) == [0]  # e.g. a SCADA polling
                time.sleep(0.05)
            assert device.state is PowerState.ENABLED  # the watchdog never tripped
            deadline = time.monotonic() + 5.0  # once the other client stops too, it does
            while device.state is not PowerState.FAULT and time.monotonic() < deadline:
                time.sleep(0.01)
            assert device.state is PowerState.FAULT
        finally:
            other.close()
            drive.close()
    with served_modbus("modbus-rtu") as (_, url), open_drive(url) as drive:
        drive.fault_code()  # no warning: an RTU line has one master (-W error would raise)


def test_a_map_with_units_per_register_sets_the_drive_units(tmp_path):
    drive = open_drive("modbus+tcp://127.0.0.1:1?map=zlac8015d")
    assert dict(drive.units) == {"u": "A", "v": "rad/s", "x": "inc"}
    assert open_drive("modbus+tcp://127.0.0.1:1?map=servobench-sim").log_metadata()["unit_v"] == "rad/s"
