"""The one place commissioning touches identification, SIDBE and the diagnosis.

Everything the steps need from :mod:`servobench.bench.procedure.sidbe` (``run_sidbe``,
``SidbeOptions``), :mod:`servobench.bench.model.servo` (``IdentificationResult``) and
:mod:`servobench.bench.diagnose.workflow` (``diagnose``, ``report.to_json``/``write_report``)
passes through here and comes out as the small result types below, so an
API change elsewhere is a fix in this module only.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from servobench.bench.model.servo import IdentificationResult, ServoModel
from servobench.drivers.base import Drive
from servobench.errors import UsageError

ProgressCallback = Callable[[int, int], None]

#: Model keys of ``servobench identify --json`` (servobench.bench.model.servo.IdentificationResult.to_json()).
IDENTIFY_KEYS = ("M", "B", "pole", "dc_gain", "coulomb_pos", "coulomb_neg", "fit_percent", "method")
#: Default SIDBE amplitude over the bump pulse that moved the axis.
AMPLITUDE_OVER_BUMP = 2.0


@dataclass(frozen=True)
class SidbeOutcome:
    """What the SIDBE procedure left behind.

    Attributes
    ----------
    result : IdentificationResult
        The accepted model (:mod:`servobench.bench.model.servo`): ``result.model`` (M, B,
        coulomb_pos, coulomb_neg, pole, dc_gain), ``std``, ``fit_percent``,
        ``method``, ``to_json()`` (the ``identify --json`` keys).
    log_path : Path
        The excitation log (all runs of the accepted experiment).
    fs_hz : float
        Cycle rate [Hz].
    plots : tuple of Path
        PNG files the procedure wrote.
    details : mapping
        Procedure facts for the record (iterations, amplitude ...), JSON-friendly.
    """

    result: IdentificationResult
    log_path: Path
    fs_hz: float
    plots: tuple[Path, ...] = ()
    details: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class DiagnoseOutcome:
    """The diagnosis of the accepted log.

    Attributes
    ----------
    effects : tuple of str
        Named effects found, most important first.
    gap_before, gap_after : float
        Model-measurement gap before and after adding the effects (the diagnosis' own unit).
    plots : tuple of Path
        PNG files the diagnosis wrote.
    details : mapping
        The diagnosis' JSON, for the record.
    note : str
        Human-readable summary.
    model : ServoModel or None
        The diagnosed model's base parameters (refitted together with the effects).
    """

    effects: tuple[str, ...] = ()
    gap_before: float = math.nan
    gap_after: float = math.nan
    plots: tuple[Path, ...] = ()
    details: Mapping[str, Any] = field(default_factory=dict)
    note: str = ""
    model: ServoModel | None = None


def sidbe_options(
    options: Mapping[str, Any], max_u: float, moved_at: float, travel_finite: bool = False
) -> Any:
    """:class:`servobench.bench.procedure.sidbe.SidbeOptions` from the ``[sidbe]`` table.

    Keys are the option names (``amplitude``, ``ratio``, ``fs_hz``, ``periods``,
    ``period_s``, ``freqs_hz``, ``loop``, ``method``, ``fit_threshold``,
    ``max_iterations``, ``growth``, ``max_amplitude``, ``settle_s``,
    ``resonance``), read and type-checked by :mod:`.config`. Without
    ``amplitude`` in open loop: twice the bump pulse that moved the axis
    (``moved_at`` [command units]), at most half of ``max_u``, so the excitation
    starts well past friction and the verification loop may still grow it up
    to max_u; in closed loop (``loop`` closed, or auto on finite travel) the
    procedure fits it to the travel. The options are validated here
    (:class:`UsageError`).
    """
    from servobench.bench.procedure.sidbe import SidbeOptions

    values = dict(options)
    loop = values.get("loop", "auto")
    closed = loop == "closed" or (loop == "auto" and travel_finite)
    if "amplitude" not in values and not closed:
        values["amplitude"] = min(AMPLITUDE_OVER_BUMP * moved_at, 0.5 * max_u)
    try:
        opts = SidbeOptions(**values, plots=True)
    except TypeError as err:
        raise UsageError(f"[sidbe]: {err}") from None
    opts.validate()
    if opts.amplitude is not None and opts.amplitude > max_u:
        raise UsageError(f"[sidbe] amplitude {opts.amplitude:g} exceeds the confirmed max_u = {max_u:g}")
    return opts


def bump_model(log_path: Path) -> Any:
    """The model the bump test's log tells (the joint estimator on its pulses), or None.

    What the closed-loop procedure designs its hold loop and excitation from; when
    the pulses cannot yield a model it learns the axis by its own relay probe.
    """
    from servobench.bench.identify.auto import identify
    from servobench.bench.log.io import read_log
    from servobench.errors import IdentificationError

    try:
        return identify(read_log(log_path), "joint").model
    except IdentificationError:
        return None


def run_sidbe(
    drive: Drive,
    options: Any,
    out_dir: Path,
    progress: ProgressCallback | None = None,
    known: Any = None,
) -> SidbeOutcome:
    """SIDBE with its verification loop on an open drive; ``log.csv``, ``log-<i>.csv`` and plots in ``out_dir``.

    ``known``: the model of the bump test (:func:`bump_model`), which a closed-loop
    run designs its hold from.
    """
    from servobench.bench.procedure import sidbe as procedure

    def tick(iteration: int, done: int, total: int) -> None:
        if progress is not None:
            progress(done, total)

    res = procedure.run_sidbe(drive, options, out_dir, progress=tick, known=known)
    summary = res.to_json()
    details = {
        "amplitude": summary["amplitude"],
        "ratio": summary["ratio"],
        "fs": summary["fs"],
        "periods": summary["periods"],
        "freqs": summary["freqs"],
        "verification": summary["verification"],
        "iterations": [
            {**it.as_dict(), "log": Path(it.log_path).name} for it in res.iterations
        ],
        "selection": res.result.selection,
        "loop": res.loop,
    }
    if res.hold is not None:
        details["hold"] = dict(res.hold)
    return SidbeOutcome(
        result=res.result,
        log_path=res.log_path,
        fs_hz=float(res.design.fs_hz),
        plots=tuple(res.plots),
        details=details,
    )


def diagnose(log_path: Path, options: Mapping[str, Any], out_dir: Path) -> DiagnoseOutcome:
    """Diagnose ``log_path`` (``[diagnose]`` keys, read by :mod:`.config`: ``horizon_s``);
    ``comparison.csv``, plots, ``report.md`` in ``out_dir``."""
    from servobench.bench.diagnose.workflow import diagnose as run_diagnosis
    from servobench.bench.log.io import read_log
    from servobench.bench.report.diagnose import to_json, write_report

    d = run_diagnosis(read_log(log_path), horizon_s=options.get("horizon_s"))
    report = write_report(d, out_dir)
    plots = tuple(sorted(report.parent.glob("*.png")))
    data = to_json(d)
    note = "no effect beyond the base model pays on held-out data" if not d.effects else "; ".join(
        f"{e.name}: {e.evidence}" for e in d.effects
    )
    note = f"{d.verdict.headline()}. {note}"  # the verdict first, as diagnose's own outputs
    return DiagnoseOutcome(
        effects=tuple(e.name for e in d.effects),
        gap_before=float(d.gap_before),
        gap_after=float(d.gap_after),
        plots=plots,
        details={k: data[k] for k in ("verdict", "noise_floor_percent", "unexplained_signature", "effects",
                                      "gap_before", "gap_after", "comparison", "findings") if k in data},  # fmt: skip
        note=note,
        model=_diagnosed_model(d.base),
    )


def _diagnosed_model(base: Mapping[str, float]) -> ServoModel | None:
    """The diagnosed base as a :class:`ServoModel`, or None when its numbers make none."""
    from servobench.errors import IdentificationError

    try:
        return ServoModel(float(base["M"]), float(base["B"]), float(base["coulomb_pos"]),
                          float(base["coulomb_neg"]))  # fmt: skip
    except (KeyError, ValueError, IdentificationError):
        return None
