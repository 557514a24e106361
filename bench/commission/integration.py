"""The one place commissioning touches identification, SIDBE and the diagnosis.

Everything the steps need from :mod:`bench.procedure`, :mod:`bench.model`
and :mod:`bench.diagnose` passes through here and comes out as the small
result types below, so an API change elsewhere is a fix in this module only.
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from drivers.base import Drive

ProgressCallback = Callable[[int, int], None]

#: Model keys of ``servobench identify --json`` (bench.model.IdentificationResult.to_json()).
IDENTIFY_KEYS = ("M", "B", "pole", "dc_gain", "coulomb_pos", "coulomb_neg", "fit_percent", "method")
#: Parameters with a 1-sigma uncertainty.
STD_KEYS = ("M", "B", "coulomb_pos", "coulomb_neg")


@dataclass(frozen=True)
class IdentifiedModel:
    """The identified model, as commissioning uses it.

    Attributes
    ----------
    M, B : float
        Linear block ``1/(M s + B)`` [command units s^2/unit, command units s/unit].
    coulomb_pos, coulomb_neg : float
        Coulomb friction magnitudes in positive / negative motion [command units].
    std : mapping
        1-sigma uncertainty of ``M``, ``B``, ``coulomb_pos``, ``coulomb_neg`` (nan when unknown).
    fit_percent : float
        Validation fit [%].
    method : str
        Estimator that produced the model.
    identify_json : mapping
        The dictionary ``servobench identify --json`` prints for this model.
    """

    M: float
    B: float
    coulomb_pos: float
    coulomb_neg: float
    std: Mapping[str, float]
    fit_percent: float
    method: str
    identify_json: Mapping[str, Any] = field(default_factory=dict)

    @property
    def pole(self) -> float:
        """``-B/M`` [1/s]."""
        return -self.B / self.M

    @property
    def dc_gain(self) -> float:
        """``1/B`` [velocity units/s per command unit]."""
        return 1.0 / self.B

    def std_derived(self) -> dict[str, float]:
        """1-sigma of pole and DC gain, first-order propagation (M, B uncorrelated)."""
        sm, sb = self.std.get("M", math.nan), self.std.get("B", math.nan)
        pole = math.hypot(sb / self.M, self.B * sm / self.M**2)
        return {"pole": pole, "dc_gain": sb / self.B**2}


@dataclass(frozen=True)
class SidbeOutcome:
    """What the SIDBE procedure left behind.

    Attributes
    ----------
    model : IdentifiedModel
    log_path : Path
        The excitation log (all runs of the accepted experiment).
    fs_hz : float
        Cycle rate [Hz].
    plots : tuple of Path
        PNG files the procedure wrote.
    details : mapping
        Procedure facts for the record (iterations, amplitude ...), JSON-friendly.
    """

    model: IdentifiedModel
    log_path: Path
    fs_hz: float
    plots: tuple[Path, ...] = ()
    details: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class DiagnoseOutcome:
    """The diagnosis of the accepted log.

    Attributes
    ----------
    available : bool
        False when this build has no diagnosis (``note`` says why).
    effects : tuple of str
        Named effects found, most important first.
    gap_before, gap_after : float
        Model-measurement gap before and after adding the effects (the diagnosis' own unit).
    plots : tuple of Path
        PNG files the diagnosis wrote.
    details : mapping
        The diagnosis' JSON, for the record.
    note : str
        Human-readable summary or why it is unavailable.
    """

    available: bool
    effects: tuple[str, ...] = ()
    gap_before: float = math.nan
    gap_after: float = math.nan
    plots: tuple[Path, ...] = ()
    details: Mapping[str, Any] = field(default_factory=dict)
    note: str = ""


def _optional(module: str):
    """Import ``module`` or return None when it is not part of this build."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as err:
        if err.name == module:
            return None
        raise


def run_sidbe(
    drive: Drive,
    options: Mapping[str, Any],
    out_dir: Path,
    progress: ProgressCallback | None = None,
) -> SidbeOutcome:
    """SIDBE with its verification loop on an open drive; writes ``log.csv`` and plots in ``out_dir``."""
    procedure = _optional("bench.procedure")
    if procedure is None:
        from bench.commission import _interim

        return _interim.run_sidbe(drive, options, out_dir, progress)
    raise NotImplementedError  # filled in when bench.procedure lands


def diagnose(log_path: Path, model: IdentifiedModel, options: Mapping[str, Any], out_dir: Path) -> DiagnoseOutcome:
    """Diagnose ``log_path`` against ``model``; results and plots in ``out_dir``."""
    if _optional("bench.diagnose") is None:
        return DiagnoseOutcome(available=False, note="this build has no bench.diagnose")
    raise NotImplementedError  # filled in when bench.diagnose lands
