"""``servobench commission`` end to end against served simulated drives (Modbus TCP, CANopen).

The drive runs in its own process (``servobench serve-sim``) and commissioning
talks to it over the real protocol stack, as in the field.
"""

from __future__ import annotations

import re

import pytest
from test_commission_cli import CONFIG, check_record

from servobench.bench.cli import main
from servobench.bench.log.io import read_log
from servobench.bench.testing.served import PATIENT_KEYS, ServedSim
from servobench.drivers.registry import open_drive

#: One candump line: ``(timestamp) channel ID#DATA [R|T]``.
CANDUMP_LINE = re.compile(r"^\(\d+\.\d+\) \S+ [0-9A-F]{3,8}#[0-9A-F]* [RT]$")


def fast(url: str) -> str:
    """The served URL with ``pace=fast`` (the lock-step drive answers as fast as asked)."""
    if "pace=" in url:
        return url
    return url + ("&" if "?" in url else "?") + "pace=fast"


def assert_left_disabled(url: str) -> None:
    with open_drive(url) as drive:
        state = drive.info().state.lower()
        assert "disabled" in state, state
        assert drive.fault_code() == 0


@pytest.mark.parametrize("transport", ["modbus-tcp", "canopen"])
def test_commission_over_a_served_drive(tmp_path, transport, capsys):
    config = tmp_path / "bench.toml"
    config.write_text(CONFIG)
    out = tmp_path / "record"
    bus = tmp_path / "bus.log"
    with ServedSim(transport, clock="lockstep") as served:
        url = fast(served.url) + PATIENT_KEYS[transport]  # a loaded machine answers late now and then
        rc = main(["commission", "--drive", url, "--yes", "--config", str(config), "--out", str(out),
                   "--record-bus", str(bus)])  # fmt: skip
        captured = capsys.readouterr()
        assert rc == 0, captured.err
        assert_left_disabled(url)
    model = check_record(out)
    drive = model["commissioning"]["drive"]
    assert drive["transport"] == url.split("://")[0]
    if transport == "canopen":
        assert drive["firmware"] and drive["serial_number"]
        assert model["identity"]["serial_number"] == drive["serial_number"]
        # the values to program in the drive's own units: per mille of its rated torque (0x6076,
        # 1000 mN m served by default) and its velocity unit, from the driver's scale factors
        meta = read_log(out / "log.csv").metadata
        assert float(meta["scale_u"]) == pytest.approx(1e-3)
        program = {p["name"]: p for p in model["program"]}
        ff = program["friction feed-forward, positive motion (Coulomb +)"]
        assert ff["unit"] == "N m" and ff["drive_value"] == pytest.approx(model["coulomb_pos"] * 1000)
        kp = program["velocity PI: proportional gain Kp"]
        assert kp["drive_value"] == pytest.approx(kp["value"] * float(meta["scale_v"]) / 1e-3)
        html = (out / "report.html").read_text()
        assert f"1 drive u unit = 0.001 N m ({meta['scale_u_source']})" in html
        lines = bus.read_text(errors="replace").splitlines()
        assert len(lines) > 1000
        assert all(CANDUMP_LINE.match(line) for line in lines), "interleaved or corrupt lines"
    else:
        assert "cannot record bus traffic" in captured.out and not bus.exists()


def test_no_motion_on_a_served_drive_refuses_and_leaves_it_disabled(tmp_path, capsys):
    config = tmp_path / "bench.toml"
    config.write_text(CONFIG)
    with ServedSim("modbus-tcp", "sim://?M=0.1&B=1&fc_pos=50&fc_neg=50", clock="lockstep") as served:
        url = fast(served.url)
        rc = main(["commission", "--drive", url, "--yes", "--config", str(config), "--out", str(tmp_path / "o")])
        assert rc == 1
        assert "no motion in the bump test" in capsys.readouterr().err
        assert_left_disabled(url)
