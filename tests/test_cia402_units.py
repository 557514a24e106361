"""CiA 402 factor group -> SI factors, against values real drives publish.

Golden unit codes come from vendors' published object dictionaries, not from
servobench: Synapticon SOMANET's 0x60A9 (1 rpm 0x00B44700, 0.1 rpm
0xFFB44700, 0.01 rpm 0xFEB44700, 0.001 rpm 0xFDB44700), an MD80 controller's
0x60A8 = 0x00B50000 ("encoder increments") and 0x60A9 = 0xFDB44700 ("milli
revolutions per minute"), the heig-vd CiA 402 stack's defaults 0x60A8 =
4244701184 (0xFD010000, mm) and 0x60A9 = 4244701952 (0xFD010300, mm/s), and
ZeroErr's eRob examples (524288 = 2**19 counts per revolution). The expected
factors are worked out by hand from the physics in each test.
"""

from __future__ import annotations

import math

import pytest

from servobench.drivers.cia402_units import (
    FactorObjects,
    Overrides,
    decode_si_unit,
    derive_scaling,
    encode_si_unit,
)
from servobench.units import LINEAR, ROTARY, SignalUnits

TWO_PI = 2.0 * math.pi


@pytest.mark.parametrize(
    ("code", "rad_s_per_lsb", "name"),
    [
        (0x00B44700, TWO_PI / 60, "rpm"),  # 11814656, Synapticon "1 RPM"
        (4290004736, TWO_PI / 600, "drpm"),  # Synapticon "0.1 RPM"
        (4273227520, TWO_PI / 6000, "crpm"),  # Synapticon "0.01 RPM"
        (4256450304, TWO_PI / 60000, "mrpm"),  # Synapticon "0.001 RPM", MD80 default
    ],
)
def test_published_velocity_units(code: int, rad_s_per_lsb: float, name: str) -> None:
    assert decode_si_unit(code).name() == name
    scaling = derive_scaling(FactorObjects(position_unit=encode_si_unit(-6, 0x10), velocity_unit=code))
    assert scaling.v.unit == "rad/s"
    assert scaling.v.scale == pytest.approx(rad_s_per_lsb, rel=1e-12)


def test_zeroerr_like_drive_without_factor_objects_keeps_its_own_units() -> None:
    # ZeroErr eDriver: 0x6076 and 0x6075 only; no 0x608F/0x6091/0x6092/0x60A8/0x60A9
    s = derive_scaling(FactorObjects(rated_torque_mNm=1270, rated_current_mA=3000))
    assert s.units == {"u": "N m", "v": "inc/s", "x": "inc"}
    assert (s.u.scale, s.v.scale, s.x.scale) == pytest.approx((1.27e-3, 1.0, 1.0))
    assert "0x6076 rated torque 1270 mN m" in s.u.source
    assert "absent" in s.x.source and "absent" in s.v.source


def test_encoder_increments_and_rpm_become_rad_and_rad_per_s() -> None:
    # MD80-style 0x60A8 = 0x00B50000 (increments), ZeroErr's 2**19 counts per revolution
    s = derive_scaling(FactorObjects(rated_torque_mNm=640, encoder=(524288, 1),
                                     position_unit=0x00B50000, velocity_unit=0x00B44700))  # fmt: skip
    assert s.units == {"u": "N m", "v": "rad/s", "x": "rad"}
    assert s.x.scale == pytest.approx(TWO_PI / 524288, rel=1e-12)
    assert s.v.scale == pytest.approx(TWO_PI / 60, rel=1e-12)
    assert s.u.scale == pytest.approx(0.64e-3, rel=1e-12)
    assert SignalUnits(**s.units) == ROTARY


def test_increments_per_second_use_the_encoder_resolution() -> None:
    s = derive_scaling(FactorObjects(encoder=(4096, 1), velocity_unit=encode_si_unit(0, 0xB5, 0x03)))
    assert (s.x.unit, s.v.unit) == ("rad", "rad/s")
    assert s.v.scale == pytest.approx(TWO_PI / 4096) == s.x.scale


def test_a_gearbox_moves_everything_to_the_driving_shaft() -> None:
    # 4096 increments per motor revolution, 10 motor revolutions per output revolution
    s = derive_scaling(FactorObjects(rated_torque_mNm=500, encoder=(4096, 1), gear=(10, 1),
                                     velocity_unit=0x00B44700))  # fmt: skip
    assert s.x.scale == pytest.approx(TWO_PI / 40960)  # rad of the output per increment
    assert s.v.scale == pytest.approx(TWO_PI / 60)  # rpm of the driving shaft
    assert s.u.scale == pytest.approx(0.5e-3 * 10)  # motor torque times the ratio
    assert "gear 10/1" in s.x.source and "gear 10/1" in s.u.source


def test_heig_vd_millimetres_make_a_linear_axis() -> None:
    s = derive_scaling(FactorObjects(position_unit=4244701184, velocity_unit=4244701952))
    assert s.linear
    assert (s.x.unit, s.v.unit) == ("m", "m/s")
    assert (s.x.scale, s.v.scale) == pytest.approx((1e-3, 1e-3))


def test_ball_screw_feed_constant_turns_torque_into_force() -> None:
    # µm positions, rpm of the screw, 5 mm lead (0x6092 = 5000 µm per revolution), 0.64 N m rated
    s = derive_scaling(FactorObjects(rated_torque_mNm=640, feed=(5000, 1),
                                     position_unit=0xFA010000, velocity_unit=0x00B44700))  # fmt: skip
    assert SignalUnits(**s.units) == LINEAR
    assert s.x.scale == pytest.approx(1e-6)
    assert s.v.scale == pytest.approx(0.005 / 60)  # one rpm moves the table 5 mm per minute
    # F = T 2 pi / lead: 0.64 mN m per LSB -> 0.64e-3 * 2 pi / 0.005 N
    assert s.u.scale == pytest.approx(0.64e-3 * TWO_PI / 0.005)
    assert "lead" in s.u.source


@pytest.mark.parametrize("feed", [None, (1, 1)], ids=["no-0x6092", "identity-0x6092"])
def test_a_linear_motor_rates_force_in_mN(feed) -> None:
    s = derive_scaling(FactorObjects(rated_torque_mNm=50000, feed=feed, position_unit=0xFA010000))
    assert s.units == {"u": "N", "v": "m/s", "x": "m"}
    assert s.u.scale == pytest.approx(0.05)
    assert "rated force 50000 mN" in s.u.source


def test_current_mode_is_amperes_unless_a_torque_constant_is_given() -> None:
    objects = FactorObjects(rated_current_mA=2500, encoder=(4096, 1))
    amps = derive_scaling(objects)
    assert (amps.u.unit, amps.u.scale) == ("A", pytest.approx(2.5e-3))
    assert "current mode" in amps.u.source
    torque = derive_scaling(objects, Overrides(torque_constant=0.12))
    assert (torque.u.unit, torque.u.scale) == ("N m", pytest.approx(2.5e-3 * 0.12))
    assert "torque_constant 0.12" in torque.u.source


def test_without_rated_torque_or_current_the_command_is_in_rated_torques() -> None:
    s = derive_scaling(FactorObjects())
    assert (s.u.unit, s.u.scale) == ("rated torque", 1e-3)


def test_url_scales_override_and_say_so() -> None:
    s = derive_scaling(FactorObjects(encoder=(4096, 1)), Overrides(pos_scale=2e-3, vel_scale=5e-4))
    assert (s.x.scale, s.x.unit, s.v.scale, s.v.unit) == (2e-3, "rad", 5e-4, "rad/s")
    assert s.x.source.startswith("URL pos_scale") and "0x608F 4096" in s.x.source
    assert s.v.source.startswith("URL vel_scale")


def test_an_unknown_unit_code_is_named_not_converted() -> None:
    s = derive_scaling(FactorObjects(position_unit=0x002C0000, velocity_unit=0x002C0300))
    assert s.x.scale == 1.0 and "0x2C" in s.x.unit
    assert s.v.scale == 1.0 and "0x2C" in s.v.unit


@pytest.mark.parametrize("exponent", [-9, -6, -3, 0, 3])
def test_unit_codes_round_trip(exponent: int) -> None:
    unit = decode_si_unit(encode_si_unit(exponent, 0xB4, 0x47))
    assert (unit.exponent, unit.numerator, unit.denominator) == (exponent, 0xB4, 0x47)
