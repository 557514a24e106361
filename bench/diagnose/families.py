"""Parameters the data cannot tell apart: a constant force against a shift of the Coulomb levels.

In motion ``M a + B v = u + offset - F_f`` with ``F_f = coulomb_pos`` (``v > 0``)
or ``-coulomb_neg`` (``v < 0``), and at rest the axis breaks away when
``u + offset`` leaves ``[-coulomb_neg, coulomb_pos]``. Only
``coulomb_pos - offset`` and ``coulomb_neg + offset`` enter: the triple
``(offset + s, coulomb_pos + s, coulomb_neg - s)`` moves the axis exactly
alike for every ``s`` that keeps both levels non-negative. The diagnosis
reports the three as one family when it matters -- the offset was named, or
the two Coulomb levels differ enough that the difference may as well be a
constant force (gravity on an inclined axis, an amplifier offset).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

#: Coulomb levels differing by more than this share of their mean are reported as a family.
ASYMMETRY = 0.25


@dataclass(frozen=True)
class Family:
    """Parameters reported together because only combinations of them are identifiable.

    Attributes
    ----------
    parameters : tuple of str
    net_pos, net_neg : float
        ``coulomb_pos - offset`` and ``coulomb_neg + offset`` [command units]: what the data fix.
    offset_range : tuple of float
        Offsets [command units] that, with the matching Coulomb levels, fit alike.
    sentence : str
    """

    parameters: tuple[str, ...]
    net_pos: float
    net_neg: float
    offset_range: tuple[float, float]
    sentence: str

    def as_dict(self) -> dict:
        return {
            "parameters": list(self.parameters),
            "net_pos": self.net_pos,
            "net_neg": self.net_neg,
            "offset_range": list(self.offset_range),
            "sentence": self.sentence,
        }


def offset_family(
    base: Mapping[str, float], effects: Mapping[str, Mapping[str, float]], unit: str
) -> Family | None:
    """The offset/Coulomb family of a final model, or None when it does not matter."""
    p, n = float(base["coulomb_pos"]), float(base["coulomb_neg"])
    named = "offset" in effects
    o = float(effects["offset"]["offset"]) if named else 0.0
    mean = 0.5 * (p + n)
    if not named and not abs(p - n) > ASYMMETRY * mean:
        return None
    net_pos, net_neg = p - o, n + o
    lo, hi = -net_pos, net_neg
    if named:
        sentence = (
            f"the offset {o:.4g} {unit} and the Coulomb levels {p:.4g} / {n:.4g} {unit} are one "
            f"family: the data fix only the friction net of the offset, {net_pos:.4g} {unit} "
            f"against positive and {net_neg:.4g} {unit} against negative motion; any offset from "
            f"{lo:.4g} to {hi:.4g} {unit} with the levels shifted to match fits alike"
        )
    else:
        sym = 0.5 * (net_pos + net_neg)
        sentence = (
            f"the Coulomb levels {p:.4g} / {n:.4g} {unit} cannot be told from equal levels of "
            f"{sym:.4g} {unit} plus a constant force of {0.5 * (net_neg - net_pos):.4g} {unit} "
            f"(an offset, gravity on an inclined axis): reported as one family, any offset from "
            f"{lo:.4g} to {hi:.4g} {unit} with the levels shifted to match fits alike"
        )
    return Family(("offset", "coulomb_pos", "coulomb_neg"), net_pos, net_neg, (lo, hi), sentence)
