"""Work on a log or a model: ``identify``, ``diagnose``, ``validate``, ``program``.

Each function is what the CLI command of the same name runs (the command parses
its arguments, calls it and prints the result); it returns a frozen result whose
``to_dict()`` is the JSON object that command prints with ``--json``
(``program``: ``--format json``); errors are the CLI's, with its one-line
messages. A log may be given as a :class:`~servobench.log.Log` or a
path, a model as a :class:`~servobench.model.Model` or the path of a model file.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from servobench.bench.log.io import ExperimentLog
from servobench.errors import UsageError
from servobench.log import Log, read_log
from servobench.model import Model, load_model, plain
from servobench.verdict import Verdict

if TYPE_CHECKING:
    from servobench.bench.commission.design import FrictionFeedForward, PIDesign
    from servobench.bench.model.program import ProgramValue

__all__ = ["Diagnosis", "ProgramValues", "Validation", "diagnose", "identify", "program", "validate"]

PathLike = str | os.PathLike[str]
#: Which column (CSV) or variable (``.mat``) holds each signal: ``"t=Time,u=Input*35.15"`` or a mapping.
ColumnMap = str | Mapping[str, str]


def _model_arg(model: Model | PathLike) -> tuple[Model, str | None]:
    """The model and the name the CLI's JSON gives it: the path as given, else the file it was
    read from or written to, else None."""
    if isinstance(model, Model):
        return model, model.source or None
    return load_model(model), os.fspath(model)


def _log_arg(log: ExperimentLog | PathLike, columns: ColumnMap | None = None,
             mat_map: ColumnMap | None = None) -> tuple[Log, str]:  # fmt: skip
    """The log and the name the CLI's output gives it: the path as given, else its source."""
    if isinstance(log, ExperimentLog):
        return Log.of(log), log.source
    return read_log(log, columns=columns, mat_map=mat_map), os.fspath(log)


# ---------------------------------------------------------------------------- identify
def identify(
    log: ExperimentLog | PathLike,
    *,
    method: str = "auto",
    resonance: bool = False,
    cutoff_hz: float | None = None,
    loop: str | None = None,
    out: PathLike | None = None,
    plots: PathLike | None = None,
    columns: ColumnMap | None = None,
    mat_map: ColumnMap | None = None,
) -> Model:
    """Identify ``M``, ``B`` and the Coulomb friction per direction, as ``servobench identify``.

    Parameters
    ----------
    log : Log or path
    method : {"auto", "sidbe", "joint"}
        ``sidbe`` needs the u1/u2 pair; ``auto`` fits both when it can and keeps the
        better on held-out data.
    resonance : bool
        Let SIDBE fit a series resonance.
    cutoff_hz : float, optional
        Cut-off of the zero-phase position filter for logs without velocity [Hz]
        (``--cutoff``; default fs/20).
    loop : {"open", "closed"}, optional
        How the log was recorded, overriding its ``loop`` metadata.
    out : path, optional
        Write ``model.json`` and the PNG plots here (refused when it holds a ``model.json``).
    plots : path, optional
        Also write the PNG plots here.
    columns, mat_map : str or mapping, optional
        Which column (CSV) or variable (``.mat``) of a log given as a path holds each signal
        (``--columns``, ``--mat-map``; see :func:`~servobench.read_log`).

    Returns
    -------
    Model
        ``to_dict()`` is the ``identify --json`` object (the model keys, ``fit_percent``,
        ``method``, ``std``, ``units`` ..., ``fs``, ``log``, ``drive_scale`` when stated);
        ``details`` the identification result the CLI's table is printed from.

    Raises
    ------
    IdentificationError
        The log cannot yield a model (no motion, too short ...).
    UsageError, LogFormatError
    """
    from servobench.bench.identify.auto import identify as identify_log
    from servobench.bench.model.program import drive_scale_json
    from servobench.bench.procedure.run_folder import MODEL_FILE

    out_dir = Path(out) if out is not None else None
    if out_dir is not None and (out_dir / MODEL_FILE).exists():
        raise UsageError(f"{out_dir} already holds a {MODEL_FILE}; choose another --out, or move it away "
                         "first: nothing was overwritten")  # fmt: skip
    log, name = _log_arg(log, columns, mat_map)
    if loop:
        log = replace(log, metadata={**log.metadata, "loop": loop})
    result = identify_log(log, method, resonance=resonance, velocity_cutoff_hz=cutoff_hz)
    folders = {Path(d) for d in (plots, out) if d is not None}
    if folders:
        from servobench.bench.report.plots import write_plots

        for folder in folders:
            folder.mkdir(parents=True, exist_ok=True)
            write_plots(result, folder)
    scale = drive_scale_json(log.metadata, name)
    doc = {**result.to_json(), "fs": log.fs_hz, "log": name, **({"drive_scale": scale} if scale else {})}
    source = ""
    if out_dir is not None:
        path = out_dir / MODEL_FILE
        path.write_text(json.dumps(doc, indent=2, allow_nan=False) + "\n", encoding="utf-8")
        source = str(path)
    return replace(Model.from_dict(plain(doc), source), details=result)


# ---------------------------------------------------------------------------- diagnose
@dataclass(frozen=True)
class Diagnosis:
    """What ``servobench diagnose`` finds: the effects the base model lacks, and whether the
    final model explains the data.

    Attributes
    ----------
    verdict : {"explained", "unexplained"}
        ``explained`` when the final gap is within reach of the noise floor.
    effects : mapping
        ``{effect name: {parameter: value}}`` of the effects added, in order, with the final
        model's parameters (``viscous_asymmetry`` also gives ``B_pos`` and ``B_neg``).
    evidence : mapping
        ``{effect name: sentence}``: the signature that named each effect.
    std : mapping
        1-sigma of every fitted value of the final model, keyed as the JSON's ``units``: the
        base (``M``, ``B``, ``coulomb_pos``, ``coulomb_neg``, ``pole``, ``dc_gain``) and
        ``"effect.parameter"`` (as ``effects`` gives them); none for parameters held fixed,
        None where the data do not determine one. ``model.std`` holds the model file's.
    model : Model
        The diagnosed plant (base refitted with the effects): the ``model.json`` of ``--out``.
    gap_percent : float
        Velocity gap [%] of the final model (NRMSE of simulated against measured velocity).
    gap_before_percent : float
        Velocity gap [%] of the base model, before any effect.
    noise_floor_percent : float
        The noise floor [%] the gap is judged against.
    notes : tuple of str
        Caveats (parameters fixed only together, a derived velocity ...).
    headline : str
        The verdict line the CLI prints first.
    report : Path or None
        ``report.md`` when ``out`` was given.
    details : servobench.bench.diagnose.workflow.Diagnosis
        The diagnosis the CLI's text is printed from (each round, the comparisons, the
        families); internal types, which may change.
    """

    verdict: str
    effects: Mapping[str, Mapping[str, float]]
    evidence: Mapping[str, str]
    std: Mapping[str, float | None]
    model: Model
    gap_percent: float
    gap_before_percent: float
    noise_floor_percent: float
    notes: tuple[str, ...]
    headline: str
    report: Path | None = None
    details: Any = field(default=None, repr=False, compare=False)
    _json: Mapping[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @property
    def explained(self) -> bool:
        return self.verdict == "explained"

    def to_dict(self) -> dict[str, Any]:
        """The object ``servobench diagnose --json`` prints (``verdict`` first)."""
        return plain(self._json)


def diagnose(
    log: ExperimentLog | PathLike,
    *,
    horizon_s: float | None = None,
    effects: Iterable[str] | None = None,
    out: PathLike | None = None,
    progress: Callable[[str], None] | None = None,
    columns: ColumnMap | None = None,
    mat_map: ColumnMap | None = None,
) -> Diagnosis:
    """Name the effect the model lacks, as ``servobench diagnose``.

    Parameters
    ----------
    log : Log or path
    horizon_s : float, optional
        Compare by predictions restarted from the measured state every ``horizon_s`` [s]
        (``--horizon``; default whole-run simulation, 0.5 s for closed-loop logs).
    effects : iterable of str, optional
        Library effects the search may name (default all).
    out : path, optional
        Write ``report.md``, ``model.json``, ``comparison.csv`` and the figures here.
    progress : callable(str), optional
        Called with a short message as each stage starts.
    columns, mat_map : str or mapping, optional
        Which column (CSV) or variable (``.mat``) of a log given as a path holds each signal
        (``--columns``, ``--mat-map``; see :func:`~servobench.read_log`).

    Raises
    ------
    IdentificationError
        The log cannot yield a base model.
    UsageError, LogFormatError
    """
    from servobench.bench.diagnose.workflow import diagnose as diagnose_log
    from servobench.bench.report.diagnose import model_json, notes, to_json, write_report

    d = diagnose_log(_log_arg(log, columns, mat_map)[0], horizon_s, effects=effects, progress=progress)
    report = None
    if out is not None:
        if progress is not None:
            progress("writing the report")
        report = write_report(d, out)
    model = Model.from_dict(model_json(d), str(report.parent / "model.json") if report else "")
    doc = plain(to_json(d))
    return Diagnosis(
        verdict=d.verdict.verdict,
        effects={e.name: dict(e.parameters) for e in d.effects},
        evidence={e.name: e.evidence for e in d.effects},
        std=dict(doc["std"]),
        model=model,
        gap_percent=float(d.gap_after),
        gap_before_percent=float(d.gap_before),
        noise_floor_percent=float(d.verdict.floor.percent),
        notes=tuple(f.sentence for f in d.families) + tuple(notes(d)),
        headline=d.verdict.headline(),
        report=report,
        details=d,
        _json=doc,
    )


# ---------------------------------------------------------------------------- validate
@dataclass(frozen=True)
class Validation:
    """How well a model reproduces a log, as ``servobench validate``.

    Attributes
    ----------
    verdict : Verdict
        PASS when ``fit_percent >= min_fit_percent`` and ``gap_percent <= max_gap_percent``.
    fit_percent : float
        ``100 (1 - ||v - v_sim|| / ||v - mean(v)||)`` over all runs [%] (``identify``'s fit).
    gap_percent : float
        NRMSE of simulated against measured velocity [%] (``diagnose``'s gap).
    force_error_percent : float or None
        Closed-loop logs: relative force error of the inverse model [%].
    notes : tuple of str
    headline : str
        The verdict line the CLI prints first.
    figure : Path or None
        ``validation.png`` when ``out`` was given.
    model : Model
        The model judged.
    details : servobench.bench.model.validate.Validation
        The comparison the CLI's text is printed from (samples, runs, how the model was
        compared); internal types, which may change.
    """

    verdict: Verdict
    fit_percent: float
    gap_percent: float
    force_error_percent: float | None
    notes: tuple[str, ...]
    headline: str
    figure: Path | None = None
    model: Model | None = None
    details: Any = field(default=None, repr=False, compare=False)
    _json: Mapping[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @property
    def passed(self) -> bool:
        return self.verdict.passed

    def to_dict(self) -> dict[str, Any]:
        """The object ``servobench validate --json`` prints (``verdict`` first)."""
        return plain(self._json)


def validate(
    model: Model | PathLike,
    log: ExperimentLog | PathLike,
    *,
    loop: str | None = None,
    min_fit_percent: float | None = None,
    max_gap_percent: float | None = None,
    out: PathLike | None = None,
    columns: ColumnMap | None = None,
    mat_map: ColumnMap | None = None,
) -> Validation:
    """Judge a saved model on another log, as ``servobench validate``.

    Parameters
    ----------
    model : Model or path of a model file
    log : Log or path
    loop : {"open", "closed"}, optional
        How the log was recorded, overriding its metadata (closed adds the force error).
    min_fit_percent, max_gap_percent : float, optional
        Thresholds [%] (``--min-fit``, ``--max-gap``; default 90 and 10).
    out : path, optional
        Write the measured-against-predicted figure here.
    columns, mat_map : str or mapping, optional
        Which column (CSV) or variable (``.mat``) of a log given as a path holds each signal
        (``--columns``, ``--mat-map``; see :func:`~servobench.read_log`).

    Raises
    ------
    IdentificationError
        The log cannot be compared (too short, nothing moves).
    UsageError, LogFormatError
    """
    from servobench.bench.model import validate as v
    from servobench.units import SignalUnits

    model, name = _model_arg(model)
    log, log_name = _log_arg(log, columns, mat_map)
    result = v.validate(model.servo_model, log, model.effects, loop=loop)
    units = SignalUnits.from_metadata(log.metadata)
    mismatch = v.unit_mismatch(model.units, units)
    if mismatch:
        result = replace(result, notes=(*result.notes, mismatch))
    figure = None
    if out is not None:
        from servobench.bench.report.validation import write_validation_figure

        figure = write_validation_figure(result, out, units, title=log.source)
    min_fit = v.DEFAULT_MIN_FIT_PERCENT if min_fit_percent is None else min_fit_percent
    max_gap = v.DEFAULT_MAX_GAP_PERCENT if max_gap_percent is None else max_gap_percent
    judged = v.judge(result, min_fit, max_gap)
    verdict = Verdict.of(judged.passed)
    doc = {"verdict": verdict.word, **result.to_json(), "thresholds": judged.as_dict(), "model": name,
           "log": log_name, "effects": list(model.effects), "units": units.as_metadata()}  # fmt: skip
    if figure is not None:
        doc["figure"] = str(figure)
    return Validation(
        verdict=verdict,
        fit_percent=float(result.fit_percent),
        gap_percent=float(result.gap_percent),
        force_error_percent=result.force_error_percent,
        notes=tuple(result.notes),
        headline=verdict.line(f"{name or 'the model'} on {log_name}: {judged.text()}"),
        figure=figure,
        model=model,
        details=result,
        _json=plain(doc),
    )


# ---------------------------------------------------------------------------- program
@dataclass(frozen=True)
class ProgramValues:
    """The values to program into the drive, as ``servobench program`` gives them.

    Iterating gives the :attr:`values`.

    Attributes
    ----------
    values : tuple of ProgramValue
        Each with ``name``, ``value`` and ``unit`` (the model's units), ``drive_value`` and
        ``drive_unit`` (the drive's own), ``note``; a text-only row has NaN values.
    feed_forward : FrictionFeedForward
        Coulomb per direction, viscous, ramp-in band.
    velocity_pi : PIDesign
        The velocity PI (``kp``, ``ki``, ``ti_s``, crossover, margins).
    source : str
        Which model the values were designed from, in one sentence.
    fs_hz : float
        The velocity-loop rate the PI is designed for [Hz].
    drive_units : str
        How the drive's units relate to the model's.
    """

    values: tuple[ProgramValue, ...]
    feed_forward: FrictionFeedForward
    velocity_pi: PIDesign
    source: str
    fs_hz: float
    drive_units: str
    _json: Mapping[str, Any] = field(default_factory=dict, repr=False, compare=False)

    def __iter__(self) -> Iterator[ProgramValue]:
        return iter(self.values)

    def __len__(self) -> int:
        return len(self.values)

    def to_dict(self) -> dict[str, Any]:
        """The object ``servobench program --format json`` prints."""
        return plain(self._json)


def program(
    model: Model | PathLike,
    *,
    fs_hz: float | None = None,
    log: ExperimentLog | PathLike | None = None,
    phase_margin_deg: float = 60.0,
    delay_cycles: float | None = None,
    sign_band: float = 0.0,
) -> ProgramValues:
    """The friction feed-forward, the velocity PI and the filter to program, from a saved model.

    Parameters
    ----------
    model : Model or path of a model file
    fs_hz : float, optional
        Velocity-loop rate the PI is designed for [Hz] (``--fs``; default the model's ``fs``).
    log : Log or path, optional
        Take the drive's scale factors (``scale_u``, ``scale_v``) from this log's header.
    phase_margin_deg : float
        Target phase margin of the PI [deg].
    delay_cycles : float, optional
        Delay beyond the zero-order hold [cycles] (default 1 plus the model's delay).
    sign_band : float
        Reference speed below which the Coulomb feed-forward ramps in [velocity units] (0: a step).

    Raises
    ------
    UsageError
        No loop rate, a negative ``sign_band``, a model file that is no model.
    """
    from servobench.bench.model.file import program_model
    from servobench.bench.model.program import DriveScale, design_values
    from servobench.model import saved_model
    from servobench.units import SignalUnits

    model, name = _model_arg(model)
    saved = saved_model(model)
    base, described = program_model(saved)
    fs = fs_hz if fs_hz is not None else saved.fs_hz
    if fs is None or not (math.isfinite(fs) and fs > 0):
        raise UsageError(f"{name or 'the model'} states no loop rate (fs): give --fs HZ, the rate of the drive's "
                         "velocity loop the PI is designed for")  # fmt: skip
    if sign_band < 0:
        raise UsageError(f"--sign-band must be >= 0, got {sign_band:g}")
    units = SignalUnits(saved.units.get("u", ""), saved.units.get("v", ""), saved.units.get("x", ""))
    scale = DriveScale()
    if log is not None:
        read, log_name = _log_arg(log)
        scale = DriveScale.from_metadata(read.metadata, log_name)
    elif saved.drive_scale:
        scale = DriveScale.from_json(saved.drive_scale, name or "the model")
    ff, pi, values = design_values(base, units, fs, scale, phase_margin_deg=phase_margin_deg,
                                   delay_cycles=delay_cycles, sign_band=sign_band)  # fmt: skip
    drive_units = ("; ".join(scale.definitions(units)) if scale.reported else
                   "none stated: the drive takes the model's units (give --log LOG with scale_u/scale_v lines)")  # fmt: skip
    rows = [{k: (None if isinstance(x, float) and math.isnan(x) else x) for k, x in v.as_dict().items()}
            for v in values]  # fmt: skip
    doc = {"model": name, "source": described, "fs": fs, "drive_units": drive_units, "values": rows,
           "feed_forward": ff.as_dict(), "velocity_pi": pi.as_dict()}  # fmt: skip
    return ProgramValues(tuple(values), ff, pi, described, float(fs), drive_units,
                         json.loads(json.dumps(doc, default=float)))  # fmt: skip

