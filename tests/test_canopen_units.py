"""Issue 15, CiA 402: a model in N m, rad/s and kg m^2 from a drive that speaks increments and rpm.

The served drive's plant is in SI (kg m^2, N m s/rad, N m); its objects speak
a realistic factor group: position in encoder increments (0x608F = 131072 per
revolution, 0x60A8 = increments), velocity in rpm (0x60A9 = 0x00B44700) and
torque in per mille of a 0.64 N m rated torque (0x6076 = 640 mN m). The URL
``serve-sim`` prints carries no scale key; the driver reads the factor group
and logs SI values, and ``servobench sidbe`` returns the SI plant.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from servobench.bench.logio import read_log
from servobench.bench.testing.served import ServedSim
from servobench.bench.testing.served_canopen import served
from servobench.drivers.registry import open_drive
from servobench.sim_backend.physics.plant import PlantParams, simulate

M, B, FC_POS, FC_NEG = 2e-4, 2e-3, 0.02, 0.016  # kg m^2, N m s/rad, N m
FACTORS = "rated_torque=0.64&inc_per_rev=131072&vel_unit=rpm"
SIM = f"sim://?M={M}&B={B}&fc_pos={FC_POS}&fc_neg={FC_NEG}&{FACTORS}"
#: 0.192 N m = 300 LSB of 0.64 mN m, and 0.9 of it 270 LSB: both levels exact on the wire.
SIDBE_ARGS = ["--fs", "50", "--periods", "3", "--freqs", "1,2,3,5,8,13", "--amplitude", "0.192"]


def test_the_driver_reads_the_factor_group_and_says_where_each_factor_came_from() -> None:
    with served(SIM) as (device, url), open_drive(url) as drive:
        assert "scale" not in url
        assert drive.units == {"u": "N m", "v": "rad/s", "x": "rad"}
        meta = drive.log_metadata()
        assert float(meta["scale_u"]) == pytest.approx(0.64e-3)
        assert float(meta["scale_v"]) == pytest.approx(2 * math.pi / 60)
        assert float(meta["scale_x"]) == pytest.approx(2 * math.pi / 131072)
        assert meta["scale_u_source"] == "0x6076 rated torque 640 mN m, per mille"
        assert meta["scale_v_source"] == "0x60A9 rpm (0x00B44700)"
        assert meta["scale_x_source"] == "0x608F 131072 inc / 1 rev, 0x6091 gear 1/1"
        assert drive.node.sdo[0x6076].raw == 640 and drive.node.sdo[0x60A8].raw == 0x00B50000
        drive.enable()
        for _ in range(400):
            fb, _ = drive.exchange(0.192)
        assert device.command == pytest.approx(0.192)  # 300 per mille of 0.64 N m
        # the SI plant's velocity, as the drive reports it in whole rpm
        rpm = device.plant.state.v * 60 / (2 * math.pi)
        assert abs(fb.velocity - device.plant.state.v) < 2 * math.pi / 60 + abs(rpm) * 1e-3
        assert fb.applied == pytest.approx(0.192, abs=0.64e-3)


def test_the_applied_command_is_the_one_on_the_wire() -> None:
    """A command between two per-mille steps is rounded once, in the Drive layer: the value
    returned as applied (and logged) is what the drive received and applies."""
    with served(SIM) as (device, url), open_drive(url) as drive:
        drive.enable()
        _, applied = drive.exchange(0.1925)  # 300.78 LSB of 0.64 mN m
        assert applied == pytest.approx(301 * 0.64e-3, rel=1e-12)
        drive.exchange(applied)
        assert device.command == pytest.approx(applied, rel=1e-12)
        assert drive.command(-0.0001) == 0.0


def test_url_scales_still_override() -> None:
    with served(SIM) as (_, url), open_drive(url + "&vel_scale=0.5") as drive:
        meta = drive.log_metadata()
        assert meta["scale_v"] == "0.5" and meta["scale_v_source"].startswith("URL vel_scale")
        assert meta["scale_x_source"].startswith("0x608F")


def test_sidbe_returns_the_si_plant(tmp_path) -> None:
    with ServedSim("canopen", SIM, clock="lockstep") as sim:
        assert not {"pos_scale", "vel_scale"} & set(sim.url.replace("&", "=").split("="))
        out = subprocess.run(
            [sys.executable, "-m", "servobench", "sidbe", "--drive", sim.url + "&pace=fast",
             "--json", "--no-plots", "--out", str(tmp_path / "run"), *SIDBE_ARGS],
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip
    assert sim.returncode == 0, sim.stderr
    assert out.returncode == 0, out.stderr
    model = json.loads(out.stdout)
    assert model["M"] == pytest.approx(M, rel=0.01)
    assert model["B"] == pytest.approx(B, rel=0.01)
    assert model["coulomb_pos"] == pytest.approx(FC_POS, rel=0.01)
    assert model["coulomb_neg"] == pytest.approx(FC_NEG, rel=0.01)
    units = {"M": "kg m^2", "B": "N m s/rad", "coulomb_pos": "N m", "coulomb_neg": "N m", "pole": "1/s"}
    assert {k: model["units"][k] for k in units} == units
    saved = json.loads((tmp_path / "run" / "model.json").read_text())
    assert {k: saved["units"][k] for k in units} == units
    meta = read_log(tmp_path / "run" / "log.csv").metadata
    assert (meta["unit_u"], meta["unit_v"], meta["unit_x"]) == ("N m", "rad/s", "rad")
    assert meta["scale_v_source"] == "0x60A9 rpm (0x00B44700)"


def test_max_rate_is_the_wire_time_of_the_mapped_cycle() -> None:
    # CAN 2.0A data frame: 47 bits + 8 per data byte, plus worst-case stuff bits
    # floor((34 + 8 n - 1) / 4) (CiA/Bosch CAN 2.0 frame layout, counted by hand):
    # RPDO1 6 bytes (controlword, target torque, torque offset) 95 + 20, RPDO2 4 bytes
    # (target position) 79 + 16, SYNC 0 bytes 47 + 8, TPDO1 8 bytes (statusword, torque
    # actual, time stamp) 111 + 24, TPDO2 8 bytes (velocity, position) 111 + 24.
    bits = 115 + 95 + 55 + 135 + 135
    with served() as (_, url):
        with open_drive(url) as drive:
            assert drive.supports_drive_hold
            assert drive.max_rate_hz() == pytest.approx(1e6 / bits)
        with open_drive(url + "&bitrate=500000") as drive:
            assert drive.max_rate_hz() == pytest.approx(5e5 / bits)
    assert math.isinf(open_drive(url).max_rate_hz())  # not open: nothing known yet


@pytest.mark.parametrize(
    ("keys", "u_per_lsb", "v_per_lsb", "source"),
    [
        # a ball screw: 5 mm lead, 0.64 N m motor, speed in rpm of the screw
        ("feed=0.005&rated_torque=0.64&vel_unit=rpm", 0.64e-3 * 2 * math.pi / 0.005, 0.005 / 60,
         "x 2 pi gear / lead"),
        # a linear motor: rated force 50 N (0x6076 = 50000 mN), speed in µm/s
        ("rated_torque=50", 0.05, 1e-6, "0x6076 rated force 50000 mN"),
    ],
    ids=["ball-screw", "linear-motor"],
)  # fmt: skip
def test_linear_axes_are_served_and_read_in_n_m_s_and_m(keys, u_per_lsb, v_per_lsb, source):
    sim = f"sim://?M=2&B=20&fc_pos=5&fc_neg=4&units=linear&{keys}"
    with served(sim) as (device, url), open_drive(url) as drive:
        assert drive.units == {"u": "N", "v": "m/s", "x": "m"}
        meta = drive.log_metadata()
        assert float(meta["scale_u"]) == pytest.approx(u_per_lsb)
        assert float(meta["scale_v"]) == pytest.approx(v_per_lsb)
        assert float(meta["scale_x"]) == pytest.approx(1e-6) and source in meta["scale_u_source"]
        applied: list[float] = []
        step = device.step
        device.step = lambda: (applied.append(device.command), step())[1]
        drive.set_cycle(0.001)
        drive.enable()
        u = 40 * u_per_lsb * np.where((np.arange(300) // 100) % 2 == 0, 1.0, -1.0)
        fb = [drive.exchange(uk)[0] for uk in u]
    np.testing.assert_allclose(applied, u, rtol=1e-9)  # whole LSBs: the force arrives exactly
    v_ref, x_ref = simulate(u, 1000.0, PlantParams(M=2, B=20, coulomb_pos=5, coulomb_neg=4))
    np.testing.assert_allclose([f.velocity for f in fb], v_ref, atol=v_per_lsb)
    np.testing.assert_allclose([f.position for f in fb], x_ref, atol=1e-6)


def test_commission_and_validate_give_the_si_model_and_the_drive_s_own_units(tmp_path, capsys) -> None:
    """The commissioning plant behind the realistic factor group (per mille of a 2 N m rated
    torque, rpm, 131072 increments per revolution): the record is in N m, rad/s and kg m^2,
    its values to program also in the drive's units, and validate reads the same model back."""
    from test_commission_cli import CONFIG, PLANT, check_record

    from servobench.bench.cli import main

    plant = "sim://?M={M}&B={B}&fc_pos={coulomb_pos}&fc_neg={coulomb_neg}".format(**PLANT)
    config = tmp_path / "bench.toml"
    config.write_text(CONFIG)
    out = tmp_path / "record"
    with ServedSim("canopen", f"{plant}&rated_torque=2&inc_per_rev=131072&vel_unit=rpm", clock="lockstep") as sim:
        assert "scale" not in sim.url
        rc = main(["commission", "--drive", sim.url + "&pace=fast", "--yes", "--config", str(config),
                   "--out", str(out)])  # fmt: skip
        assert rc == 0, capsys.readouterr().err
    model = check_record(out)  # pole and DC gain of the SI plant within 1 %
    for key in ("M", "B", "coulomb_pos", "coulomb_neg"):
        assert model[key] == pytest.approx(PLANT[key], rel=0.03), key
    units = {"M": "kg m^2", "B": "N m s/rad", "coulomb_pos": "N m", "pole": "1/s"}
    assert {k: model["units"][k] for k in units} == units
    meta = read_log(out / "log.csv").metadata
    assert (meta["unit_u"], meta["unit_v"], meta["unit_x"]) == ("N m", "rad/s", "rad")
    rpm = 2 * math.pi / 60
    assert (float(meta["scale_u"]), float(meta["scale_v"])) == pytest.approx((0.002, rpm))
    program = {p["name"]: p for p in model["program"]}
    ff = program["friction feed-forward, positive motion (Coulomb +)"]
    assert ff["unit"] == "N m" and ff["drive_value"] == pytest.approx(ff["value"] / 0.002)
    kp = program["velocity PI: proportional gain Kp"]
    assert kp["unit"] == "N m s/rad" and kp["drive_value"] == pytest.approx(kp["value"] * rpm / 0.002)
    # 1 rpm steps in the velocity are noise of 1 rpm/sqrt(12) to the diagnosis, not an unexplained gap
    report = (out / "diagnose" / "report.md").read_text()
    assert "**verdict: explained" in report and "reported in steps of 0.1047 rad/s" in report
    html = (out / "report.html").read_text()
    assert "1 drive u unit = 0.002 N m (0x6076 rated torque 2000 mN m, per mille)" in html
    assert "1 drive v unit = 0.10472 rad/s (0x60A9 rpm (0x00B44700))" in html
    # validate: the record's model against its own log, in the same units, nothing to warn of
    capsys.readouterr()
    assert main(["validate", str(out / "model.json"), str(out / "log.csv"), "--json"]) == 0
    checked = json.loads(capsys.readouterr().out)
    assert checked["units"] == {"unit_u": "N m", "unit_v": "rad/s", "unit_x": "rad"}
    assert not [n for n in checked["notes"] if "units" in n] and checked["fit_percent"] > 90


def test_the_served_factor_group_can_come_from_the_drive_s_eds(tmp_path) -> None:
    """A drive's EDS with its factor group as default values (a 1.27 N m motor, a 10000-count
    encoder behind a 5:1 gear, position in increments, velocity in rpm): served with no factor keys, the driver reads
    exactly those objects and scales to the driving shaft (behind the gear) in SI."""
    from importlib import resources

    text = resources.files("servobench.drivers").joinpath("data/cia402.eds").read_text("ascii")

    def set_default(section: str, value: str) -> None:
        nonlocal text
        head = text.index(f"[{section}]\n")
        at = text.index("DefaultValue=", head)
        end = text.index("\n", at)
        text = text[:at] + f"DefaultValue={value}" + text[end:]

    set_default("6076", "1270")
    set_default("608Fsub1", "10000")
    set_default("6091sub1", "5")
    set_default("60A8", "0x00B50000")  # position in increments
    set_default("60A9", "0x00B44700")  # velocity in rpm
    eds = tmp_path / "drive.eds"
    eds.write_text(text, encoding="ascii")
    plant = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"
    with served(plant, eds=str(eds)) as (_, url), open_drive(url) as drive:
        meta = drive.log_metadata()
    assert drive.units == {"u": "N m", "v": "rad/s", "x": "rad"}
    assert float(meta["scale_u"]) == pytest.approx(1.27e-3 * 5)  # torque at the load: x gear
    assert meta["scale_u_source"].startswith("0x6076 rated torque 1270 mN m, per mille")
    assert meta["scale_v_source"].startswith("0x60A9 rpm (0x00B44700)")
    assert "0x608F 10000 inc / 1 rev" in meta["scale_x_source"] and "gear 5/1" in meta["scale_x_source"]
    assert float(meta["scale_x"]) == pytest.approx(2 * math.pi / (10000 * 5))
    assert float(meta["scale_v"]) == pytest.approx(2 * math.pi / 60)  # rpm of the driving shaft
