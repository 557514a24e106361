"""The values to program into the drive, in SI and in the drive's own units.

Peer: CiA 402's definitions of the drive's units -- the command in per mille
of the rated torque 0x6076, velocity in the unit 0x60A9 names (rpm here),
position in encoder increments 0x608F -- worked by hand for a drive rated
0.64 N m with a 17-bit encoder, as a technician would convert them.
"""

from __future__ import annotations

import math

import pytest

from servobench.bench.commission.design import design_pi, friction_feed_forward
from servobench.bench.model.program import DriveScale, program_values
from servobench.bench.model.servo import Resonance, ServoModel
from servobench.errors import LogFormatError
from servobench.units import ROTARY, SignalUnits

MODEL = ServoModel(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)
#: Log header lines of such a drive (SI per drive unit, as the CANopen driver writes them).
METADATA = {
    "unit_u": "N m", "unit_v": "rad/s", "unit_x": "rad",
    "scale_u": "0.00064", "scale_u_source": "0x6076 rated torque 640 mN m, per mille",
    "scale_v": "0.10471975512", "scale_v_source": "0x60A9 rpm (0x00B44700)",
    "scale_x": "4.79368996e-05", "scale_x_source": "0x608F 131072 inc / 1 rev",
}  # fmt: skip


def _values(scale: DriveScale, model: ServoModel = MODEL, units: SignalUnits = ROTARY) -> dict:
    ff = friction_feed_forward(model.B, model.coulomb_pos, model.coulomb_neg, 0.02)
    pi = design_pi(model.M, model.B, 1000.0)
    return {v.name: v for v in program_values(model, ff, pi, units, scale)}, pi


def test_values_in_the_drives_own_units_by_hand():
    values, pi = _values(DriveScale.from_metadata(METADATA))
    pos = values["friction feed-forward, positive motion (Coulomb +)"]
    assert (pos.value, pos.unit) == (0.5, "N m")
    assert pos.drive_value == pytest.approx(781.25)  # 0.5 N m / 0.64 N m x 1000 per mille
    assert values["friction feed-forward, negative motion (Coulomb -)"].drive_value == pytest.approx(625.0)
    viscous = values["viscous feed-forward (B)"]
    assert viscous.unit == "N m s/rad"
    # 1 N m per rad/s: 1 rpm = 2 pi / 60 rad/s asks 0.10472 N m = 163.62 per mille
    assert viscous.drive_value == pytest.approx(1.0 * (2 * math.pi / 60) / 0.00064, rel=1e-9)
    assert viscous.drive_value == pytest.approx(163.62, abs=0.01)
    band = values["feed-forward ramp-in band"]
    assert band.drive_value == pytest.approx(0.02 / (2 * math.pi / 60))  # rad/s -> rpm
    kp, ki = values["velocity PI: proportional gain Kp"], values["velocity PI: integral gain Ki = Kp/Ti"]
    assert kp.drive_value == pytest.approx(pi.kp * (2 * math.pi / 60) / 0.00064)
    assert ki.unit == "N m/rad" and ki.drive_value == pytest.approx(pi.ki * (2 * math.pi / 60) / 0.00064)
    assert kp.drive_unit == "(drive u unit)/(drive v unit)"
    ti = values["velocity PI: integral time Ti"]
    assert ti.value == ti.drive_value == pytest.approx(pi.ti_s) and ti.unit == "s"


def test_the_definitions_name_each_factor_and_its_source():
    scale = DriveScale.from_metadata(METADATA)
    assert scale.reported
    assert scale.definitions(ROTARY) == [
        "1 drive u unit = 0.00064 N m (0x6076 rated torque 640 mN m, per mille)",
        "1 drive v unit = 0.10472 rad/s (0x60A9 rpm (0x00B44700))",
        "1 drive x unit = 4.79369e-05 rad (0x608F 131072 inc / 1 rev)",
    ]


def test_without_scale_factors_the_drive_takes_the_logged_units():
    scale = DriveScale.from_metadata({"unit_u": "N m", "unit_v": "rad/s"})
    assert not scale.reported
    values, _ = _values(scale)
    for v in values.values():
        if not math.isnan(v.value):
            assert v.drive_value == v.value and v.drive_unit == v.unit


def test_a_bad_scale_factor_is_one_clear_line():
    with pytest.raises(LogFormatError, match=r"^run/log.csv: metadata scale_v = 'fast' must be a finite") as err:
        DriveScale.from_metadata({"scale_v": "fast"}, "run/log.csv")
    assert "\n" not in str(err.value)
    with pytest.raises(LogFormatError, match="scale_u = '0'"):
        DriveScale.from_metadata({"scale_u": "0"})


def test_the_filter_row_follows_the_model():
    values, pi = _values(DriveScale())
    assert math.isnan(values["velocity filter"].value) and "no resonance" in values["velocity filter"].note
    resonant = ServoModel(0.1, 1.0, 0.5, 0.4, Resonance(2 * math.pi * 80.0, 0.05))
    values, _ = _values(DriveScale(), resonant)
    notch = values["notch filter centre frequency"]
    assert notch.value == pytest.approx(80.0) and notch.unit == "Hz" and "damping 0.05" in notch.note


def test_unknown_units_are_named_not_left_blank():
    values, _ = _values(DriveScale(), units=SignalUnits())
    assert values["viscous feed-forward (B)"].unit == "(command unit)/(velocity unit)"
    assert values["velocity PI: integral gain Ki = Kp/Ti"].unit == "((command unit)/(velocity unit))/s"
