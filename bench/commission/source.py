"""Which model the values to program come from, and how the identification step is judged (pure).

The SIDBE base model (linear block and Coulomb per direction) is what the
procedure verified against its threshold. When the diagnosis of the same log
names an effect the base model lacks and, with it, closes the velocity gap,
the base fit is biased by the missing effect (backlash lowers the Coulomb
levels SIDBE sees), and the diagnosed model -- the base refitted together
with the effects -- is the better account of the axis: the friction
feed-forward and the PI are then designed from *its* base parameters, and
the record says so.

The identification step then passes when the model the values come from
reaches the threshold: the SIDBE fit, or the diagnosed model's fit
``100 - gap_after`` (the diagnosis' NRMSE gap, the same measure).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from servobench.bench.model.servo import ServoModel

#: ``ProgramSource.model`` of each origin.
SIDBE, DIAGNOSE = "sidbe", "diagnose"


@dataclass(frozen=True)
class ProgramSource:
    """The model the values to program are designed from.

    Attributes
    ----------
    model : ServoModel
        Its base parameters (M, B, Coulomb per direction; the SIDBE resonance kept).
    origin : str
        :data:`SIDBE` (the verified SIDBE model) or :data:`DIAGNOSE` (the diagnosed model).
    description : str
        One sentence a reader of the record understands.
    fit_percent : float
        Its fit to the log [%]: SIDBE's verification fit, or ``100 - gap_after``.
    threshold : float
        The verification threshold [%].
    base_passed : bool
        Whether the SIDBE base fit reached the threshold by itself.
    """

    model: ServoModel
    origin: str
    description: str
    fit_percent: float
    threshold: float
    base_passed: bool

    @property
    def passed(self) -> bool:
        return self.fit_percent >= self.threshold

    def as_dict(self) -> dict[str, object]:
        """``program_source`` of ``model.json``."""
        m = self.model
        return {
            "model": self.origin, "description": self.description, "fit_percent": self.fit_percent,
            "threshold": self.threshold, "passed": self.passed, "base_passed": self.base_passed,
            "M": m.M, "B": m.B, "coulomb_pos": m.coulomb_pos, "coulomb_neg": m.coulomb_neg,
        }  # fmt: skip


def choose_source(
    base: ServoModel,
    base_fit: float,
    threshold: float,
    effects: tuple[str, ...] = (),
    diagnosed: ServoModel | None = None,
    gap_before: float = math.nan,
    gap_after: float = math.nan,
    diagnosis_file: str = "diagnose/model.json",
) -> ProgramSource:
    """The model to program from: the diagnosed one when its effects close the gap, else the base."""
    base_passed = base_fit >= threshold
    closes = bool(effects) and diagnosed is not None and math.isfinite(gap_after) and gap_after < gap_before
    if not closes:
        return ProgramSource(base, SIDBE, "the SIDBE model (linear block and Coulomb friction per "
                             "direction), verified by simulation", base_fit, threshold, base_passed)  # fmt: skip
    assert diagnosed is not None
    named = " + ".join(effects)
    model = ServoModel(diagnosed.M, diagnosed.B, diagnosed.coulomb_pos, diagnosed.coulomb_neg,
                       resonance=base.resonance)  # fmt: skip
    description = (f"the diagnosed model: the base refitted together with {named} ({diagnosis_file}), "
                   f"which closes the velocity gap from {gap_before:.3g} % to {gap_after:.3g} %")  # fmt: skip
    return ProgramSource(model, DIAGNOSE, description, 100.0 - gap_after, threshold, base_passed)
