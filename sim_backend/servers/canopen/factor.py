"""The served CiA 402 drive's factor group: how its objects speak the plant's SI units.

The plant of the simulated drive is defined in SI: command in N m (N on a
linear axis, A for a current-mode drive), velocity in rad/s or m/s, position
in rad or m. Its objects speak what a real drive speaks, chosen by the
``sim://`` keys of ``serve-sim --transport canopen`` (:data:`SIM_KEYS`), else by
the default values in its EDS, else by the defaults below:

``rated_torque`` [N m]
    0x6076 = 1000 x this [mN m]; 0x6071/0x6077/0x60B2 are per mille of it
    (default 1). A linear axis's command is the force the screw gives.
``rated_current`` [A]
    0x6075 [mA]; the drive is in current mode when its object dictionary
    has 0x6075 but not 0x6076: per mille of the rated current (default 1).
``inc_per_rev``
    Encoder increments per motor revolution (0x608F); naming it makes
    0x6064 count increments (0x60A8 = inc). Default 524288 where the
    object dictionary has no 0x60A8 (a 19-bit encoder, as on ZeroErr's
    eRob joints), else the EDS's own 0x60A8 unit, else µrad.
``vel_unit``
    0x606C in ``rpm`` (0x60A9 = 0x00B44700), ``mrpm`` (0.001 rpm),
    ``inc/s``, ``urad/s`` or ``um/s``; default the EDS's 0x60A9, else µrad/s
    (µm/s on a linear axis), else (no 0x60A9) position units per second.
``gear``
    Motor revolutions per driving shaft revolution, an integer (0x6091).
``feed`` [m]
    Travel per driving shaft revolution (0x6092): the axis is linear, its
    position in µm (0x60A8 = 0xFA010000).
``units``
    The plant's own ``sim://`` key: ``linear`` without a ``feed`` is a linear
    motor: position in µm, velocity in µm/s, 0x6076 its rated force [mN]
    (``rated_torque`` in N) and 0x6092 the identity 1/1.

The conversions here are written from the physics of each unit, apart from
the host's derivation (:mod:`servobench.drivers.cia402_units`); only the CiA
303-2 unit-code table is shared, to read unit codes from an EDS.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from canopen.objectdictionary import ObjectDictionary, ODVariable

from servobench.drivers.cia402_units import (
    CODE_INC,
    CODE_M,
    CODE_MIN,
    CODE_RAD,
    CODE_REV,
    CODE_S,
    UNIT_CODES,
    decode_si_unit,
    encode_si_unit,
)
from servobench.errors import DriveConfigError

#: ``sim://`` keys of the served CiA 402 drive (factor group and position loop gains).
SIM_KEYS = frozenset(
    {"rated_torque", "rated_current", "inc_per_rev", "vel_unit", "gear", "feed",
     "pos_kp", "pos_ki", "pos_kd", "units"}
)  # fmt: skip
#: ``vel_unit`` values and their 0x60A9 codes.
VEL_UNITS = {
    "rpm": encode_si_unit(0, CODE_REV, CODE_MIN),
    "mrpm": encode_si_unit(-3, CODE_REV, CODE_MIN),
    "inc/s": encode_si_unit(0, CODE_INC, CODE_S),
    "urad/s": encode_si_unit(-6, CODE_RAD, CODE_S),
    "um/s": encode_si_unit(-6, CODE_M, CODE_S),
}
MICRORADIAN = encode_si_unit(-6, CODE_RAD)
MICROMETRE = encode_si_unit(-6, CODE_M)
INCREMENTS = encode_si_unit(0, CODE_INC)
#: Encoder resolution where neither key nor EDS says one [increments per revolution].
DEFAULT_INC_PER_REV = 2**19


def _default(od: ObjectDictionary, index: int, sub: int = 0) -> int | None:
    """The EDS's value of ``index:sub``, ``None`` when absent or without one."""
    if index not in od:
        return None
    obj = od[index]
    if not isinstance(obj, ODVariable):
        if sub not in obj:
            return None
        obj = obj[sub]
    value = obj.value if obj.value is not None else obj.default
    return int(value) if isinstance(value, (int, float)) and value else None


def _number(keys: Mapping[str, str], key: str) -> float | None:
    if key not in keys:
        return None
    try:
        value = float(keys[key])
    except ValueError:
        raise DriveConfigError(f"sim key {key}={keys[key]!r} is not a number") from None
    if not (math.isfinite(value) and value > 0):
        raise DriveConfigError(f"sim key {key}={keys[key]!r} must be a positive number")
    return value


@dataclass(frozen=True)
class ServedFactors:
    """What the served drive's objects mean, and the conversions to and from the plant."""

    rated_torque_Nm: float | None  # None: the object dictionary has no 0x6076
    rated_current_A: float | None
    inc_per_rev: int
    gear: int
    feed_m: float | None  # linear axis: travel per driving shaft revolution
    linear: bool  # a linear axis (on a screw when feed_m is given, else a linear motor)
    position_code: int  # 0x60A8
    velocity_code: int  # 0x60A9

    @property
    def current_mode(self) -> bool:
        return self.rated_torque_Nm is None and self.rated_current_A is not None

    @classmethod
    def from_config(cls, keys: Mapping[str, str], od: ObjectDictionary) -> ServedFactors:
        """From the ``sim://`` keys, else the EDS defaults, else the module's defaults."""
        unknown = set(keys) - SIM_KEYS
        if unknown:
            raise DriveConfigError(f"unknown served CANopen key(s): {', '.join(sorted(unknown))}")
        torque = _number(keys, "rated_torque") or (_default(od, 0x6076) or 1000) / 1000
        current = _number(keys, "rated_current") or (_default(od, 0x6075) or 1000) / 1000
        eds_pos, eds_vel = _default(od, 0x60A8), _default(od, 0x60A9)
        feed = _number(keys, "feed") or _eds_feed(od, eds_pos)
        axis = keys.get("units", "")
        linear = (
            bool(feed)
            or axis == "linear"
            or bool(eds_pos and decode_si_unit(eds_pos).kind == "length")
        )
        if axis == "rotary" and linear:
            raise DriveConfigError(
                "units=rotary with a feed constant: a screw makes the axis linear"
            )
        gear = _number(keys, "gear") or (_default(od, 0x6091, 1) or 1) / (
            _default(od, 0x6091, 2) or 1
        )
        if gear != int(gear):
            raise DriveConfigError(f"gear {gear:g} must be a whole number of motor revolutions")
        inc_key = _number(keys, "inc_per_rev")
        eds_inc = _default(od, 0x608F, 1)
        inc = int(
            inc_key
            or (eds_inc // (_default(od, 0x608F, 2) or 1) if eds_inc else DEFAULT_INC_PER_REV)
        )
        if linear:
            position = (
                eds_pos if eds_pos and decode_si_unit(eds_pos).kind == "length" else MICROMETRE
            )
        elif inc_key or 0x60A8 not in od:
            position = INCREMENTS
        else:
            position = eds_pos or MICRORADIAN
        velocity = cls._velocity_code(keys, od, eds_vel, position, linear, feed)
        unit = decode_si_unit(velocity)
        if linear and not feed and unit.numerator not in (CODE_M,) and 0x60A9 in od:
            raise DriveConfigError(f"a linear motor (no feed) cannot speak {unit.name()}: use um/s")
        return cls(
            rated_torque_Nm=torque if 0x6076 in od else None,
            rated_current_A=current if 0x6075 in od else None,
            inc_per_rev=inc, gear=int(gear), feed_m=feed, linear=linear,
            position_code=position, velocity_code=velocity,
        )  # fmt: skip

    @staticmethod
    def _velocity_code(keys, od, eds_vel, position, linear, feed) -> int:
        if "vel_unit" in keys:
            if keys["vel_unit"] not in VEL_UNITS:
                raise DriveConfigError(
                    f"sim key vel_unit={keys['vel_unit']!r}: choose {', '.join(VEL_UNITS)}"
                )
            return VEL_UNITS[keys["vel_unit"]]
        if 0x60A9 not in od:  # the host then reads position units per second
            unit = decode_si_unit(position)
            return encode_si_unit(unit.exponent, unit.numerator, CODE_S)
        kind = decode_si_unit(eds_vel).kind if eds_vel else ""
        if kind == "angle" and linear and not feed:  # the EDS's rotary default, on a linear motor
            eds_vel = None
        return eds_vel or VEL_UNITS["um/s" if linear else "urad/s"]

    # ------------------------------------------------------- plant <-> objects
    def _increments_per_unit(self) -> float:
        """Encoder increments per rad (per m on a linear axis) at the driving shaft."""
        per_turn = self.inc_per_rev * self.gear
        return per_turn / self.feed_m if self.feed_m else per_turn / (2.0 * math.pi)

    def position_raw(self, x: float) -> float:
        """0x6064 for position ``x`` [rad or m] (before rounding)."""
        unit = decode_si_unit(self.position_code)
        if unit.numerator == CODE_INC:
            return x * self._increments_per_unit() / 10.0**unit.exponent
        return x / (10.0**unit.exponent * UNIT_CODES[unit.numerator][1])

    def velocity_raw(self, v: float) -> float:
        """0x606C for velocity ``v`` [rad/s or m/s] (before rounding)."""
        unit = decode_si_unit(self.velocity_code)
        per_s = 10.0**unit.exponent / UNIT_CODES[unit.denominator][1]  # seconds^-1 per LSB
        if unit.numerator == CODE_INC:
            return v * self._increments_per_unit() / per_s
        one = UNIT_CODES[unit.numerator][1]  # SI of one numerator unit
        if self.feed_m and UNIT_CODES[unit.numerator][2] == "angle":
            one = one / (2.0 * math.pi) * self.feed_m  # a revolution of the screw moves feed_m
        return v / (per_s * one)

    def command_per_lsb(self) -> float:
        """Plant command per LSB of 0x6071/0x6077/0x60B2."""
        if self.current_mode:
            return self.rated_current_A / 1000.0
        rated = 1.0 if self.rated_torque_Nm is None else self.rated_torque_Nm
        if self.linear and not self.feed_m:  # a linear motor: 0x6076 is its rated force
            return rated / 1000.0
        if self.feed_m:  # motor torque through gear and screw: F = T 2 pi i / p
            return rated / 1000.0 * 2.0 * math.pi * self.gear / self.feed_m
        return rated / 1000.0 * self.gear

    def od_values(self) -> dict[tuple[int, int], int]:
        """The factor-group objects' values (the served node keeps those it has)."""
        x_unit = decode_si_unit(self.position_code)
        if x_unit.numerator == CODE_INC:
            per_rev = self.inc_per_rev * self.gear
        elif self.linear and not self.feed_m:
            per_rev = 1  # a linear motor: CiA 402's identity 1/1
        else:
            per_rev = self.position_raw(self.feed_m or 2.0 * math.pi)
        values = {
            (0x6075, 0): round((self.rated_current_A or 1.0) * 1000),
            (0x608F, 1): self.inc_per_rev, (0x608F, 2): 1,
            (0x6091, 1): self.gear, (0x6091, 2): 1,
            (0x6092, 1): round(per_rev), (0x6092, 2): 1,
            (0x60A8, 0): self.position_code, (0x60A9, 0): self.velocity_code,
        }  # fmt: skip
        if self.rated_torque_Nm is not None:
            values[(0x6076, 0)] = round(self.rated_torque_Nm * 1000)
        return values


def _eds_feed(od: ObjectDictionary, eds_pos: int | None) -> float | None:
    """Feed per driving shaft revolution [m] from an EDS whose 0x60A8 is a length."""
    if not eds_pos or decode_si_unit(eds_pos).kind != "length":
        return None
    feed, revs = _default(od, 0x6092, 1), _default(od, 0x6092, 2) or 1
    unit = decode_si_unit(eds_pos)
    return None if not feed else feed / revs * 10.0**unit.exponent * UNIT_CODES[unit.numerator][1]


def encode(od: ObjectDictionary, index: int, sub: int, value: int) -> bytes:
    """``value`` in the type the object dictionary gives ``index:sub``."""
    obj = od[index]
    var = obj if isinstance(obj, ODVariable) else obj[sub]
    return var.encode_raw(value)
