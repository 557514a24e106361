"""Units of the signals of a log and of the parameters identified from it.

A log names the units of its three signals in its metadata::

    # unit_u = N m          command (torque)  -- N for a linear axis, A for current mode
    # unit_v = rad/s        velocity          -- m/s
    # unit_x = rad          position          -- m

SI units are written exactly as in this table (``"N m"``, ``"N"``, ``"A"``,
``"rad/s"``, ``"m/s"``, ``"rad"``, ``"m"``). Anything else is a drive's own
unit named as such (``"rpm"``, ``"inc"``, ``"per mille of rated torque"``),
and an empty string means not known. The parameters of
``M dv/dt + B v = u - F_f`` then have the units :meth:`SignalUnits.parameters`
derives: ``M`` in [u]/([v]/s), ``B`` in [u]/[v], the Coulomb levels in [u],
the pole in 1/s and the DC gain in [v]/[u]; for the SI pairs these read
kg m^2, N m s/rad and N m (rotary) or kg, N s/m and N (linear).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

#: Metadata key of each signal's unit.
METADATA_KEYS = {"u": "unit_u", "v": "unit_v", "x": "unit_x"}

#: Parameter units of the SI signal pairs (command unit, velocity unit).
_SI_PARAMETERS: dict[tuple[str, str], dict[str, str]] = {
    ("N m", "rad/s"): {"M": "kg m^2", "B": "N m s/rad", "dc_gain": "rad/(N m s)"},
    ("N", "m/s"): {"M": "kg", "B": "N s/m", "dc_gain": "m/(N s)"},
    ("A", "rad/s"): {"M": "A s^2/rad", "B": "A s/rad", "dc_gain": "rad/(A s)"},
    ("A", "m/s"): {"M": "A s^2/m", "B": "A s/m", "dc_gain": "m/(A s)"},
}
#: What an unknown unit is called where a unit must be shown.
_UNNAMED = {"u": "command unit", "v": "velocity unit", "x": "position unit"}


def _group(unit: str) -> str:
    """``unit`` as one factor of a product or quotient: parenthesised when compound."""
    return f"({unit})" if any(c in unit for c in " /*^") else unit


@dataclass(frozen=True)
class SignalUnits:
    """Units of command ``u``, velocity ``v`` and position ``x``; ``""`` where not known.

    Examples
    --------
    >>> SignalUnits("N m", "rad/s", "rad").parameters()["M"]
    'kg m^2'
    >>> SignalUnits("per mille", "rpm", "inc").parameters()["B"]
    '(per mille)/rpm'
    """

    u: str = ""
    v: str = ""
    x: str = ""

    @classmethod
    def from_metadata(cls, metadata: Mapping[str, str]) -> SignalUnits:
        """The units a log's ``unit_u``/``unit_v``/``unit_x`` lines state."""
        return cls(**{k: str(metadata.get(key, "")).strip() for k, key in METADATA_KEYS.items()})

    def as_metadata(self) -> dict[str, str]:
        """``unit_u``/``unit_v``/``unit_x`` lines for the known units."""
        return {key: getattr(self, k) for k, key in METADATA_KEYS.items() if getattr(self, k)}

    @property
    def known(self) -> bool:
        """True when command and velocity units are both known (the parameters then are)."""
        return bool(self.u and self.v)

    @property
    def si(self) -> bool:
        """True when command and velocity are an SI pair (N m and rad/s, N and m/s, A and ...)."""
        return (self.u, self.v) in _SI_PARAMETERS

    def of(self, signal: str) -> str:
        """The unit of ``signal`` (``"u"``, ``"v"`` or ``"x"``), named even when unknown."""
        return getattr(self, signal) or _UNNAMED[signal]

    def label(self, signal: str, name: str | None = None) -> str:
        """An axis label such as ``"v [rad/s]"``."""
        return f"{name or signal} [{self.of(signal)}]"

    def parameters(self) -> dict[str, str]:
        """The unit of every identified parameter, by its JSON key.

        Keys ``M``, ``B``, ``coulomb_pos``, ``coulomb_neg``, ``pole``,
        ``dc_gain``, and the signals ``u``, ``v``, ``x``; unknown signal
        units are named generically ("command unit", ...).
        """
        u, v, x = self.of("u"), self.of("v"), self.of("x")
        derived = _SI_PARAMETERS.get((self.u, self.v)) or {
            "M": f"{_group(u)} s/{_group(v)}",
            "B": f"{_group(u)}/{_group(v)}",
            "dc_gain": f"{_group(v)}/{_group(u)}",
        }
        return {
            "M": derived["M"],
            "B": derived["B"],
            "coulomb_pos": u,
            "coulomb_neg": u,
            "pole": "1/s",
            "dc_gain": derived["dc_gain"],
            "u": u,
            "v": v,
            "x": x,
        }

    def effect_parameter(self, unit: str) -> str:
        """An effect parameter's unit in these signal units.

        The effect library declares its parameters in units relative to the axis
        (``"command units"``, ``"units/s"``, ``"units"``, ``"command units*s/unit"``);
        this names them as the log or drive does. Absolute units (``"s"``, ``"rad"``
        of a phase, ``"Hz"``) are returned unchanged.

        >>> ROTARY.effect_parameter("command units"), LINEAR.effect_parameter("units/s")
        ('N m', 'm/s')
        """
        table = {
            "command units": self.of("u"),
            "units/s": self.of("v"),
            "units": self.of("x"),
            "command units*s/unit": self.parameters()["B"],
        }
        return table.get(unit, unit)


#: A rotary axis in SI units.
ROTARY = SignalUnits("N m", "rad/s", "rad")
#: A linear axis in SI units.
LINEAR = SignalUnits("N", "m/s", "m")
