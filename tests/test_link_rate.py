"""The cycle rate must fit the link (issue 10 §4): each drive's limit, the default rate, the refusal.

The limits are the wire arithmetic of :mod:`servobench.drivers.link_budget`
applied to what one cycle puts on the wire; they are checked here against
frame sizes counted by hand from the Modbus specifications and the ODrive
ASCII protocol, not against the code that computes them.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from servobench.bench.cli import main
from servobench.drivers.link_budget import default_rate_hz, sample_rate_hz
from servobench.drivers.registry import open_drive
from servobench.errors import UsageError

RTU = "modbus+rtu:///dev/ttyUSB7?baud=115200&unit=1&map=servobench-sim"


def test_modbus_rtu_limit_is_the_frames_of_one_fc23_cycle():
    # FC23 request: addr, fc, read addr 2, read qty 2, write addr 2, write qty 2, byte count,
    # 4 data bytes (an int32 command), CRC 2 = 17 bytes; response: addr, fc, byte count,
    # 16 data bytes (8 feedback registers), CRC 2 = 21 bytes (Application Protocol v1.1b3 §6.17).
    wire_s = (17 + 21) * 10 / 115200 + 2 * 1.75e-3  # 8N1 characters, t3.5 after each frame
    turnaround_s = 0.5e-3  # servobench-sim.toml: turnaround_ms = 0.5, per transaction: one
    drive = open_drive(RTU)
    assert drive.max_rate_hz() == pytest.approx(1 / (wire_s + turnaround_s), rel=1e-9)
    assert drive.log_metadata()["link_max_rate_hz"] == f"{1 / (wire_s + turnaround_s):.1f}"


def test_modbus_rtu_limit_without_fc23_and_at_9600_baud(tmp_path):
    shipped = Path(open_drive(RTU).regmap.path).read_text()
    path = tmp_path / "nofc23.toml"
    path.write_text(shipped.replace("fc23 = true", "fc23 = false"))
    drive = open_drive(RTU.replace("115200", "9600").replace("servobench-sim", str(path)))
    # FC16 write of 2 registers: 13 bytes out, 8 back; FC03 read of 8: 8 out, 21 back
    char_s, gap_s = 10 / 9600, 3.5 * 11 / 9600  # t3.5 of 11-bit characters below 19200 baud
    cycle_s = (13 + 8 + 8 + 21) * char_s + 4 * gap_s + 2 * 0.5e-3
    assert drive.max_rate_hz() == pytest.approx(1 / cycle_s, rel=1e-9)


def test_serial_limit_counts_the_odrive_lines():
    drive = open_drive("serial:///dev/ttyACM7?baud=115200&poll=0")
    # "c 0 -1.234567\n" (14) + "f 0\n" (4) out, "-12.345678 -1.234567\r\n" (22) back
    assert drive.max_rate_hz() == pytest.approx(115200 / 10 / (14 + 4 + 22), rel=1e-9)
    polled = open_drive("serial:///dev/ttyACM7?baud=115200&poll=0.1")
    # plus "r axis0.error\n" (14) and "0\r\n" (3) ten times a second
    busy = 10 * 17 * 10 / 115200
    assert polled.max_rate_hz() == pytest.approx((1 - busy) * 115200 / 10 / 40, rel=1e-9)


def test_default_rate_is_a_round_rate_with_margin():
    assert default_rate_hz(128.3, 1000) == 100
    assert default_rate_hz(283.7, 1000) == 200
    assert default_rate_hz(1600, 1000) == 1000
    assert default_rate_hz(math.inf, 1000) == 1000
    assert default_rate_hz(30, 1000) == 20
    with pytest.raises(ValueError):
        default_rate_hz(0.5, 1000)


def test_a_rate_beyond_the_link_is_refused_naming_what_it_carries():
    assert sample_rate_hz(None, 128.3, 1000) == 100
    assert sample_rate_hz(120, 128.3, 1000) == 120
    with pytest.raises(UsageError, match=r"--fs 1000 Hz is beyond the link: it carries at most 128 "):
        sample_rate_hz(1000, 128.3, 1000)


@pytest.mark.parametrize("command", ["sidbe", "run"])
def test_cli_refuses_at_once_before_opening_the_port(command, tmp_path, capsys):
    # the port does not exist: the refusal comes before any attempt to open it
    extra = ["--out", str(tmp_path / ("log.csv" if command == "run" else "out"))]
    assert main([command, "--drive", RTU, "--fs", "1000", *extra]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "--fs 1000 Hz is beyond the modbus+rtu:// link: it carries at most 137 cycles/s" in err
    assert "use --fs 100" in err
    assert not (tmp_path / "out").exists() and not (tmp_path / "log.csv").exists()
