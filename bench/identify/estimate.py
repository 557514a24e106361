"""What an identification method returns before verification (internal to bench)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from servobench.bench.model.servo import ServoModel


@dataclass(frozen=True)
class MethodEstimate:
    """A method's model and how it got there.

    Attributes
    ----------
    model : ServoModel
    method : str
        ``"sidbe"`` or ``"joint"``.
    std : mapping
        1-sigma of ``M``, ``B``, ``coulomb_pos``, ``coulomb_neg``.
    estimator : str
        The estimator that produced the final numbers.
    noise_std : float
        Velocity noise estimate [units/s].
    notes : tuple of str
    frf : FrequencyResponse or None
    """

    model: ServoModel
    method: str
    std: Mapping[str, float]
    estimator: str
    noise_std: float = 0.0
    notes: tuple[str, ...] = ()
    frf: Any = field(default=None)
