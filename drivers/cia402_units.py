"""CiA 402 factor group -> SI scale factors of the command, velocity and position.

Pure: no I/O. The host (:mod:`servobench.drivers.canopen.drive`) reads the objects
below where the drive has them and calls :func:`derive_scaling`; the served
drive (:mod:`servobench.sim_backend.servers.canopen.factor`) decodes its own unit
codes with :func:`decode_si_unit`.

Objects (CiA 402-2; absent ones are ``None`` in :class:`FactorObjects`)::

    0x6075     motor rated current [mA]
    0x6076     motor rated torque [mN m]; rated force [mN] of a linear motor
    0x608F:1/2 position encoder resolution: encoder increments / motor revolutions
    0x6091:1/2 gear ratio: motor revolutions / driving shaft revolutions
    0x6092:1/2 feed constant: feed [position units] / driving shaft revolutions
    0x60A8     SI unit position      } bits 31..24 prefix 10^n (signed), 23..16 unit,
    0x60A9     SI unit velocity      } 15..8 denominator unit, 7..0 reserved (CiA 303-2 codes)

What the values mean (every factor is "SI per LSB" of the object):

* position 0x6064 / 0x607A: in the unit 0x60A8 names when it is a length or
  an angle (``0xFA010000`` µm, ``0xFD010000`` mm, ``0xFA100000`` µrad, a
  degree or a revolution), else in encoder increments: 0x608F increments per
  motor revolution, divided by the gear ratio 0x6091, give radians of the
  driving shaft. A length unit makes the axis linear.
* velocity 0x606C: in the unit 0x60A9 names (``0x00B44700`` rpm, a prefix
  such as ``0xFDB44700`` for 0.001 rpm, increments or lengths per second);
  revolutions are of the driving shaft, and on a linear axis a revolution is
  the feed 0x6092 of one driving shaft revolution. Without 0x60A9 the velocity
  is taken as position units per second.
* command 0x6071 / 0x6077 / 0x60B2: per mille of the rated torque 0x6076
  (rated force on a linear motor: a linear axis without a feed constant,
  or with CiA 402's identity 0x6092 = 1/1),
  times the gear ratio at the driving shaft; on a linear axis with a feed
  constant, ``F = T 2 pi i / lead``. A drive without 0x6076 but with 0x6075
  is a current-mode drive: per mille of the rated current, in A, or in N m
  when the URL gives a torque constant (N/A on a linear motor).

Whatever cannot be converted keeps the drive's own unit, named as such
(``inc``, ``inc/s``, ``rpm``, ``rated torque``). The URL keys ``pos_scale``
and ``vel_scale`` override the derived position and velocity factors (SI of
the axis kind per LSB). Each :class:`Factor` says where it came from.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: CiA 303-2 unit codes servobench converts: code -> (symbol, SI value of one unit, kind).
UNIT_CODES: dict[int, tuple[str, float, str]] = {
    0x00: ("", 1.0, "none"),
    0x01: ("m", 1.0, "length"),
    0x03: ("s", 1.0, "time"),
    0x10: ("rad", 1.0, "angle"),
    0x41: ("deg", math.pi / 180.0, "angle"),
    0x47: ("min", 60.0, "time"),
    0xB4: ("rev", 2.0 * math.pi, "angle"),
    0xB5: ("inc", 1.0, "increments"),
}
#: SI prefixes by exponent, for naming the drive's own units.
PREFIXES = {-9: "n", -6: "u", -3: "m", -2: "c", -1: "d", 0: "", 3: "k"}

#: Unit codes of the SI units, for the served drive and the tests.
CODE_M, CODE_S, CODE_RAD, CODE_MIN, CODE_REV, CODE_INC = 0x01, 0x03, 0x10, 0x47, 0xB4, 0xB5


@dataclass(frozen=True)
class SiUnit:
    """A decoded 0x60A8 / 0x60A9 value: ``10**exponent * numerator / denominator``."""

    exponent: int
    numerator: int
    denominator: int

    @property
    def known(self) -> bool:
        return self.numerator in UNIT_CODES and self.denominator in UNIT_CODES

    @property
    def kind(self) -> str:
        """``length``, ``angle``, ``increments`` (or ``unknown``) of the numerator."""
        return UNIT_CODES[self.numerator][2] if self.numerator in UNIT_CODES else "unknown"

    def name(self) -> str:
        """The unit as the drive names it: ``rpm``, ``um``, ``mrev/min``, ``0x60A9 0x2C``."""
        if not self.known:
            return f"unit code 0x{self.numerator:02X}/0x{self.denominator:02X}"
        prefix = PREFIXES.get(self.exponent, f"1e{self.exponent} ")
        num, den = UNIT_CODES[self.numerator][0], UNIT_CODES[self.denominator][0]
        if (num, den) == ("rev", "min"):
            return f"{prefix}rpm"
        return f"{prefix}{num}/{den}" if den else f"{prefix}{num}"


def decode_si_unit(code: int) -> SiUnit:
    """Split a 0x60A8/0x60A9 value into prefix exponent, unit and denominator codes."""
    exponent = (code >> 24) & 0xFF
    exponent -= 0x100 if exponent >= 0x80 else 0
    return SiUnit(exponent, (code >> 16) & 0xFF, (code >> 8) & 0xFF)


def encode_si_unit(exponent: int, numerator: int, denominator: int = 0) -> int:
    """The 0x60A8/0x60A9 value of ``10**exponent * numerator / denominator``."""
    return (exponent & 0xFF) << 24 | numerator << 16 | denominator << 8


@dataclass(frozen=True)
class FactorObjects:
    """The factor-group objects as read from a drive; ``None`` where it lacks them."""

    rated_torque_mNm: int | None = None  # 0x6076
    rated_current_mA: int | None = None  # 0x6075
    encoder: tuple[int, int] | None = None  # 0x608F increments, motor revolutions
    gear: tuple[int, int] | None = None  # 0x6091 motor revolutions, shaft revolutions
    feed: tuple[int, int] | None = None  # 0x6092 feed, shaft revolutions
    position_unit: int | None = None  # 0x60A8
    velocity_unit: int | None = None  # 0x60A9


@dataclass(frozen=True)
class Overrides:
    """What the URL says instead: ``pos_scale``, ``vel_scale``, ``torque_constant``."""

    pos_scale: float | None = None
    vel_scale: float | None = None
    torque_constant: float | None = None


@dataclass(frozen=True)
class Factor:
    """One signal's factor: ``value = raw * scale`` in ``unit``; ``source`` says why."""

    scale: float
    unit: str
    source: str


@dataclass(frozen=True)
class Scaling:
    """The factors of command ``u``, velocity ``v`` and position ``x``."""

    u: Factor
    v: Factor
    x: Factor
    linear: bool

    @property
    def units(self) -> dict[str, str]:
        return {"u": self.u.unit, "v": self.v.unit, "x": self.x.unit}


def _ratio(pair: tuple[int, int] | None) -> float | None:
    """``a / b`` of a (numerator, denominator) object pair, ``None`` if absent or zero."""
    if pair is None or not pair[0] or not pair[1]:
        return None
    return pair[0] / pair[1]


def _pair(name: str, pair: tuple[int, int] | None) -> str:
    return f", {name} {pair[0]}/{pair[1]}" if pair else ""


def _increment(obj: FactorObjects, lead_m: float | None, linear: bool) -> Factor | None:
    """One encoder increment at the driving shaft (rad, or m on a linear axis), if known."""
    per_rev, gear = _ratio(obj.encoder), _ratio(obj.gear) or 1.0
    if per_rev is None or (linear and lead_m is None):
        return None
    turns = 1.0 / (per_rev * gear)  # driving shaft revolutions per increment
    source = f"0x608F {obj.encoder[0]} inc / {obj.encoder[1]} rev{_pair('0x6091 gear', obj.gear)}"
    if linear:
        return Factor(turns * lead_m, "m", f"{source}{_pair('0x6092 feed', obj.feed)}")
    return Factor(turns * 2.0 * math.pi, "rad", source)


def _position(obj: FactorObjects) -> tuple[Factor, bool]:
    """Position factor and whether the axis is linear."""
    if obj.position_unit is None:
        inc = _increment(obj, None, False)
        return inc or Factor(1.0, "inc", "0x60A8 and 0x608F absent: the drive's increments"), False
    unit = decode_si_unit(obj.position_unit)
    source = f"0x60A8 {unit.name()} (0x{obj.position_unit:08X})"
    if unit.kind in ("length", "angle"):
        linear = unit.kind == "length"
        scale = 10.0**unit.exponent * UNIT_CODES[unit.numerator][1]
        return Factor(scale, "m" if linear else "rad", source), linear
    if unit.kind == "increments":
        inc = _increment(obj, None, False)
        return inc or Factor(10.0**unit.exponent, "inc", f"{source}, 0x608F absent"), False
    return Factor(1.0, unit.name(), f"{source}: not a length or an angle"), False


def _lead_m(obj: FactorObjects, x: Factor, linear: bool) -> float | None:
    """Travel of one driving shaft revolution [m] on a linear axis (0x6092), or ``None``.

    0x6092 = 1/1 is CiA 402's default, the identity a linear motor's drive keeps:
    no screw (a lead of one position unit would be absurd).
    """
    if not linear or obj.feed is None or obj.feed[0] == obj.feed[1]:
        return None
    feed = _ratio(obj.feed)
    return None if feed is None else feed * x.scale


def _velocity(obj: FactorObjects, x: Factor, linear: bool) -> Factor:
    if obj.velocity_unit is None:
        return Factor(
            x.scale, f"{x.unit}/s", f"0x60A9 absent: position units per second ({x.source})"
        )
    unit = decode_si_unit(obj.velocity_unit)
    source = f"0x60A9 {unit.name()} (0x{obj.velocity_unit:08X})"
    if not unit.known or UNIT_CODES[unit.denominator][2] != "time":
        return Factor(1.0, unit.name(), f"{source}: not a speed servobench converts")
    per_s = 10.0**unit.exponent / UNIT_CODES[unit.denominator][1]
    lead = _lead_m(obj, x, linear)
    if unit.kind == "increments":
        inc = _increment(obj, lead, linear)
        if inc is None:
            return Factor(per_s, "inc/s", f"{source}, 0x608F absent")
        return Factor(per_s * inc.scale, f"{inc.unit}/s", f"{source}, {inc.source}")
    if unit.kind == "length" and linear:
        return Factor(per_s * UNIT_CODES[unit.numerator][1], "m/s", source)
    if unit.kind == "angle" and not linear:
        return Factor(per_s * UNIT_CODES[unit.numerator][1], "rad/s", source)
    if unit.kind == "angle" and lead is not None:
        turns = per_s * UNIT_CODES[unit.numerator][1] / (2.0 * math.pi)
        return Factor(turns * lead, "m/s", f"{source}{_pair('0x6092 feed', obj.feed)}")
    return Factor(1.0, unit.name(), f"{source}: does not match the position unit {x.unit}")


def _command(obj: FactorObjects, linear: bool, x: Factor, kt: float | None) -> Factor:
    gear = _ratio(obj.gear) or 1.0
    lead = _lead_m(obj, x, linear)
    motor_linear = linear and lead is None  # a linear axis without a screw: a linear motor
    # motor torque -> the axis's own quantity: times the gear ratio, through the screw to force
    to_axis = 2.0 * math.pi * gear / lead if lead else gear
    if lead:
        conversion = f", x 2 pi gear / lead ({lead:.6g} m)"
    else:
        conversion = _pair("x 0x6091 gear", obj.gear) if gear != 1.0 else ""
    unit = "N" if linear else "N m"
    if obj.rated_torque_mNm:
        rated = f"rated force {obj.rated_torque_mNm} mN" if motor_linear else (
            f"rated torque {obj.rated_torque_mNm} mN m")  # fmt: skip
        return Factor(obj.rated_torque_mNm / 1e6 * to_axis, unit,
                      f"0x6076 {rated}, per mille{conversion}")  # fmt: skip
    if obj.rated_current_mA:
        amps = obj.rated_current_mA / 1e6  # A per LSB
        source = f"0x6075 rated current {obj.rated_current_mA} mA, per mille (current mode)"
        if kt is None:
            return Factor(amps, "A", f"{source}; no torque_constant in the URL")
        return Factor(
            amps * kt * to_axis, unit, f"{source}, URL torque_constant {kt:g}{conversion}"
        )
    return Factor(1e-3, "rated torque", "0x6076 and 0x6075 absent: rated torques")


def derive_scaling(obj: FactorObjects, overrides: Overrides = Overrides()) -> Scaling:
    """The factors of ``u``, ``v`` and ``x`` from the drive's factor group and the URL.

    Examples
    --------
    >>> s = derive_scaling(FactorObjects(rated_torque_mNm=640, encoder=(131072, 1),
    ...                                  position_unit=0x00B50000, velocity_unit=0x00B44700))
    >>> s.units
    {'u': 'N m', 'v': 'rad/s', 'x': 'rad'}
    >>> round(s.u.scale, 8), round(s.v.scale, 6)
    (0.00064, 0.10472)
    """
    x, linear = _position(obj)
    v = _velocity(obj, x, linear)
    kind = ("m", "m/s") if linear else ("rad", "rad/s")
    if overrides.pos_scale is not None:
        x = Factor(overrides.pos_scale, kind[0], f"URL pos_scale (drive: {x.source})")
    if overrides.vel_scale is not None:
        v = Factor(overrides.vel_scale, kind[1], f"URL vel_scale (drive: {v.source})")
    return Scaling(_command(obj, linear, x, overrides.torque_constant), v, x, linear)
