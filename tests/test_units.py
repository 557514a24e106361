"""Units of signals and parameters (servobench.units)."""

from __future__ import annotations

import pytest

from servobench.units import LINEAR, ROTARY, SignalUnits


def test_rotary_and_linear_si_parameters():
    rot = ROTARY.parameters()
    assert (rot["M"], rot["B"], rot["coulomb_pos"], rot["coulomb_neg"], rot["pole"]) == (
        "kg m^2", "N m s/rad", "N m", "N m", "1/s",
    )  # fmt: skip
    lin = LINEAR.parameters()
    assert (lin["M"], lin["B"], lin["coulomb_pos"], lin["pole"]) == ("kg", "N s/m", "N", "1/s")
    assert ROTARY.si and LINEAR.si and ROTARY.known


def test_a_drives_own_units_compose_and_are_named_as_such():
    own = SignalUnits("per mille of rated torque", "rpm", "inc").parameters()
    assert own["M"] == "(per mille of rated torque) s/rpm"
    assert own["B"] == "(per mille of rated torque)/rpm"
    assert own["dc_gain"] == "rpm/(per mille of rated torque)"
    assert own["coulomb_pos"] == "per mille of rated torque"
    assert not SignalUnits("per mille", "rpm").si


def test_unknown_units_are_named_generically_and_not_known():
    none = SignalUnits()
    assert not none.known and not none.si
    assert none.parameters()["B"] == "(command unit)/(velocity unit)"
    assert none.label("v") == "v [velocity unit]"
    assert ROTARY.label("x", "position") == "position [rad]"


@pytest.mark.parametrize("units", [ROTARY, LINEAR, SignalUnits("A", "rad/s", ""), SignalUnits()])
def test_metadata_round_trip(units):
    meta = units.as_metadata()
    assert all(meta.values())  # unknown units are not written
    assert SignalUnits.from_metadata(meta) == units
    assert SignalUnits.from_metadata({"unit_u": "  N m ", "fs": "1000"}).u == "N m"


def test_a_log_without_units_gives_generic_parameter_units(tmp_path):
    from servobench.bench.identify.auto import identify
    from servobench.bench.log.io import read_log

    rows = []
    v = 0.0
    for k in range(4000):  # a noise-free first-order plant, u = +-1 square wave, no friction
        u = 1.0 if (k // 500) % 2 == 0 else -1.0
        rows.append(f"{k / 1000:.3f},{u},{v:.12g}")
        v += (u - v) * (1 - 2.718281828459045 ** -0.01)
    path = tmp_path / "plain.csv"
    path.write_text("# fs = 1000\nt,u,v\n" + "\n".join(rows) + "\n")
    log = read_log(path)
    assert log.units == SignalUnits()
    units = identify(log, "joint").to_json()["units"]
    assert units["B"] == "(command unit)/(velocity unit)" and units["pole"] == "1/s"
    path.write_text("# fs = 1000\n# unit_u = N\n# unit_v = m/s\nt,u,v\n" + "\n".join(rows) + "\n")
    assert identify(read_log(path), "joint").to_json()["units"]["M"] == "kg"


def test_sim_units_key_is_checked():
    from servobench.drivers.registry import open_drive
    from servobench.errors import DriveConfigError

    with pytest.raises(DriveConfigError, match="rotary"):
        open_drive("sim://?units=imperial")
