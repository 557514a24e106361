"""``Drive.open(read_only=True)`` writes nothing on Modbus and serial, counted at the served drive.

Each served drive runs in a thread of the test process, and what it received
is recorded where it handles it (the Modbus PDU handler, the serial line
handler), as a peer sees it. Modbus: a map with a ``[[setup]]`` write and a
watchdog fed by a register, so that a plain open, a read and a close write
three ways (the control); read-only, no write function code (5, 6, 15, 16,
23) reaches the drive, ``commission --dry-run`` included. Serial (ODrive
firmware 0.5.6): a plain open disarms the watchdog and clears a stale
watchdog error; read-only sends only reads: no ``w``, ``c``, ``u`` or ``sc``,
and the stale error stays for the next writable session to clear.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from importlib.resources import files

import pytest

from servobench.bench.cli import main
from servobench.bench.testing.served_modbus import served_modbus
from servobench.drivers.registry import open_drive
from servobench.errors import DriveFaultError, DriveWarning, UsageError
from servobench.sim_backend.device import SimulatedDevice, WatchdogThread, device_from_url
from servobench.sim_backend.servers.modbus.pdu import PduHandler
from servobench.sim_backend.servers.serial import serve_serial
from servobench.sim_backend.servers.serial.serve_serial import AsciiDriveServer

SIM = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"
#: Modbus function codes that write (coils, registers, read/write multiple).
MODBUS_WRITES = frozenset({5, 6, 15, 16, 23})
#: ODrive ASCII requests that write: a property, a torque command, a watchdog feed, clear errors.
SERIAL_WRITES = ("w ", "c ", "u ", "sc")
#: ODrive's axis error for a watchdog that expired (firmware 0.5.x).
WATCHDOG_TIMER_EXPIRED = 0x800
#: Time for the last lines of a session to reach the served drive [s].
SETTLE_S = 0.3
CONFIG = """
[limits]
max_u = 2.0
max_v = 20.0
xmin = -inf
xmax = inf
"""
#: The served map, with a set-up write at open and a watchdog fed by a register every cycle.
SETUP_AND_FEED = """
[[setup]]
address = 0x0001
value = 400
note = "watchdog 0.4 s, as a drive's mode selection would be written"

[registers.watchdog_feed]
address = 0x0030
format = "uint16"
"""


@pytest.fixture
def modbus_codes(monkeypatch) -> list[int]:
    """The function code of every request the served Modbus drive handles."""
    codes: list[int] = []
    handle = PduHandler.handle

    def recording(self, pdu: bytes) -> bytes:
        codes.append(pdu[0])
        return handle(self, pdu)

    monkeypatch.setattr(PduHandler, "handle", recording)
    return codes


def _map(tmp_path) -> str:
    text = (files("servobench.drivers") / "data" / "maps" / "servobench-sim.toml").read_text()
    text = text.replace('feed = "any_request"', 'feed = "register"')
    path = tmp_path / "setup-and-feed.toml"
    text = text.replace('name = "servobench-sim"', 'name = "setup-and-feed"', 1)
    path.write_text(text + SETUP_AND_FEED)
    return str(path)


def _writes(codes: list[int]) -> list[int]:
    return [c for c in codes if c in MODBUS_WRITES]


def test_modbus_read_only_open_writes_no_setup_no_feed_no_command(tmp_path, modbus_codes) -> None:
    with served_modbus("modbus-tcp", SIM, map=_map(tmp_path)) as (_device, url):
        with read_only(url) as drive:
            for _ in range(5):
                drive.read()
            drive.info()
            drive.fault_code()
            with pytest.raises(UsageError, match="read-only"):
                drive.enable()
        dry = list(modbus_codes)
        with open_drive(url) as plain:  # the control: set-up, watchdog, and a feed per read
            plain.read()
        plain_codes = modbus_codes[len(dry) :]
    assert len(dry) > 7  # it did read the drive
    assert _writes(dry) == [], dry
    assert len(_writes(plain_codes)) >= 3, plain_codes


def test_modbus_dry_run_with_setup_and_feed_writes_nothing(tmp_path, modbus_codes) -> None:
    with served_modbus("modbus-tcp", SIM, map=_map(tmp_path)) as (_device, url):
        (tmp_path / "bench.toml").write_text(CONFIG)
        rc = main(["commission", "--drive", url, "--dry-run", "--yes", "--config",
                   str(tmp_path / "bench.toml"), "--out", str(tmp_path / "record")])  # fmt: skip
    assert rc == 0
    assert modbus_codes and _writes(modbus_codes) == [], modbus_codes


# ---------------------------------------------------------------------- serial
@contextmanager
def served_serial(device: SimulatedDevice, firmware: str = "0.5.6") -> Iterator[str]:
    """The ODrive stand-in firmware on a pty in a thread; yields its drive URL."""
    stop, urls = threading.Event(), queue.Queue()
    errors: list[BaseException] = []

    def run() -> None:
        try:
            serve_serial.serve(device, stop, urls.put, {"firmware": firmware})
        except BaseException as err:
            errors.append(err)
            urls.put(None)

    watchdog = WatchdogThread(device)  # trips the device's watchdog, as the served process does
    watchdog.start()
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    url = urls.get(timeout=10)
    try:
        if url is None:
            raise errors[0]
        yield url
    finally:
        stop.set()
        thread.join(5)
        watchdog.stop()
    assert not errors, errors


@pytest.fixture
def serial_lines(monkeypatch) -> list[str]:
    """Every request line the served serial drive handles."""
    lines: list[str] = []
    handle = AsciiDriveServer.handle

    def recording(self, raw: bytes) -> bytes:
        lines.append(raw.decode("ascii", "replace").strip())
        return handle(self, raw)

    monkeypatch.setattr(AsciiDriveServer, "handle", recording)
    return lines


def _after(session, lines: list[str]) -> list[str]:
    """The lines the served drive handled during ``session()`` (given time to arrive)."""
    start = len(lines)
    session()
    time.sleep(SETTLE_S)
    return lines[start:]


def _serial_writes(lines: list[str]) -> list[str]:
    return [line for line in lines if line.startswith(SERIAL_WRITES)]


def test_serial_read_only_open_sends_only_reads(serial_lines) -> None:
    import serial

    with served_serial(device_from_url(SIM)) as url:
        path = url.split("://")[1].split("?")[0]
        with serial.Serial(path, 115200, timeout=0.2) as old_host:  # arms its watchdog, goes away
            for line in (b"w axis0.config.watchdog_timeout 0.1", b"u 0",
                         b"w axis0.config.enable_watchdog 1"):  # fmt: skip
                old_host.write(line + b"\n")
            old_host.flush()
        time.sleep(1.0)  # watchdog 0.1 s: it tripped, and the error latched
        seen: dict = {}

        def stale_session() -> None:
            with read_only(url) as drive:
                seen["stale"], seen["info"] = drive.fault_code(), drive.info()
                with pytest.raises(DriveFaultError):  # a read that finds the fault says so
                    drive.read()
                with pytest.raises(UsageError, match="read-only"):
                    drive.enable()

        def plain_session() -> None:  # the control: disarms, clears the stale error, disarms
            with pytest.warns(DriveWarning, match="cleared"), open_drive(url) as plain:
                seen["cleared"] = plain.fault_code()

        def clean_session() -> None:
            with read_only(url) as drive:
                seen["rows"] = [drive.read() for _ in range(5)]

        dry = _after(stale_session, serial_lines)
        control = _after(plain_session, serial_lines)
        dry_again = _after(clean_session, serial_lines)
    assert seen["stale"] == WATCHDOG_TIMER_EXPIRED == seen["info"].fault_code  # left as found
    assert len(seen["rows"]) == 5, seen
    assert sum(line.startswith("r ") for line in dry_again) >= 10, dry_again
    assert _serial_writes(dry) == [] and _serial_writes(dry_again) == [], (dry, dry_again)
    assert seen["cleared"] == 0 and "sc" in control, control
    assert any(line.startswith("w ") for line in control), control


@contextmanager
def read_only(url: str) -> Iterator:
    drive = open_drive(url)
    drive.open(read_only=True)
    try:
        yield drive
    finally:
        drive.close()
