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
