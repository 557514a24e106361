"""Work on a drive or a fleet: ``sidbe``, ``commission``, ``fleet``.

Each function is what the CLI command of the same name runs: the command parses
its arguments, calls it and prints the result (the terminal output is the
command's: no progress bars or notes unless ``progress`` and ``note`` callbacks
are given; ``commission`` talks at the terminal as the CLI does). Each returns a
frozen result whose ``to_dict()`` is the JSON the command prints (``--json``) or,
for ``commission``, writes (``commission.json``). Errors are the CLI's.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from servobench.bench.procedure.sidbe import Iteration, SidbeOptions
from servobench.errors import IdentificationError, UsageError, add_note
from servobench.model import Model, load_model, plain
from servobench.verdict import Verdict

if TYPE_CHECKING:
    from servobench.bench.fleet.table import FleetRow
    from servobench.bench.fleet.trend import AxisTrend
    from servobench.drivers.base import Drive

__all__ = ["CommissionResult", "FleetResult", "SidbeResult", "commission", "fleet", "sidbe"]

PathLike = str | os.PathLike[str]
_DEFAULT = SidbeOptions()


# ---------------------------------------------------------------------------- sidbe
@dataclass(frozen=True)
class SidbeResult:
    """The outcome of the whole SIDBE procedure on a drive, as ``servobench sidbe``.

    Attributes
    ----------
    model : Model
        The accepted (or, when the threshold was never met, the best) model: ``model.json``.
    verdict : Verdict
        PASS when the verification fit reached ``fit_threshold`` and the run's timing keeps the
        model within its stated accuracy; PASS with remarks when the fit reached it but the
        timing does not (exit status 0: the model fits, its parameters may be off by more than
        stated; ``model.timing`` says how far and what to change); else FAIL (the CLI's first
        line and exit status 3).
    log : Path
        ``log.csv``: the round the model was identified from.
    fit_percent : float
        Verification fit of the model [%].
    fit_threshold : float
        The fit [%] that passes.
    out_dir : Path
        The run folder.
    model_file : Path
        ``model.json`` in it.
    plots : tuple of Path
        The PNG plots written.
    iterations : tuple of Iteration
        Each excite-identify round: amplitude, lines, fit, what came next.
    headline : str
        The verdict line the CLI prints first.
    pace : {"real", "fast"}
        How the runs were streamed: in real time, or lock-step as fast as the drive answers.
    link_max_hz : float
        The highest cycle rate the drive's link carries [Hz] (``inf``: nothing bounds it).
    details : servobench.bench.procedure.sidbe.SidbeResult
        The procedure's own record, which the CLI's text is printed from (the excitation
        design, the achieved rate, the hold loop, the drive's remarks, the identification
        result); internal types, which may change.
    """

    model: Model
    verdict: Verdict
    log: Path
    fit_percent: float
    fit_threshold: float
    out_dir: Path
    model_file: Path
    plots: tuple[Path, ...]
    iterations: tuple[Iteration, ...]
    headline: str
    pace: str = "real"
    link_max_hz: float = math.inf
    details: Any = field(default=None, repr=False, compare=False)
    _json: Mapping[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @property
    def passed(self) -> bool:
        return self.verdict.passed

    def to_dict(self) -> dict[str, Any]:
        """The object ``servobench sidbe --json`` prints, the content of ``model.json``."""
        return plain(self._json)


def sidbe(
    drive: Drive | str,
    out: PathLike | None = None,
    *,
    amplitude: float | None = _DEFAULT.amplitude,
    ratio: float = _DEFAULT.ratio,
    fs_hz: float | None = _DEFAULT.fs_hz,
    periods: int = _DEFAULT.periods,
    period_s: float = _DEFAULT.period_s,
    freqs_hz: Sequence[float] | None = _DEFAULT.freqs_hz,
    loop: str = _DEFAULT.loop,
    method: str = _DEFAULT.method,
    fit_threshold: float = _DEFAULT.fit_threshold,
    max_iterations: int = _DEFAULT.max_iterations,
    max_amplitude: float | None = _DEFAULT.max_amplitude,
    resonance: bool = _DEFAULT.resonance,
    plots: bool = _DEFAULT.plots,
    growth: float = _DEFAULT.growth,
    pace: str | None = _DEFAULT.pace,
    settle_s: float = _DEFAULT.settle_s,
    axis: str = _DEFAULT.axis,
    progress: Callable[[int, int, int], None] | None = None,
    note: Callable[[str], None] | None = None,
) -> SidbeResult:
    """Run the whole SIDBE procedure on a drive, as ``servobench sidbe``.

    Designs the excitation, streams u1 and u2, identifies and verifies the model, repeats
    with a larger amplitude (or a redesigned spectrum) while the fit is below the
    threshold, and writes ``log.csv``, ``model.json`` and the plots to ``out``.

    Parameters
    ----------
    drive : Drive or str
        A drive (from :func:`servobench.open_drive`; opened here and closed again when it is
        not open yet), or a drive URL.
    out : path, optional
        The run folder, new or empty (default a new ``./servobench-runs/<timestamp>``).
    amplitude, ratio, fs_hz, periods, period_s, freqs_hz, loop, method, fit_threshold, max_iterations, max_amplitude, resonance
        The CLI's options ``--amplitude`` [command units], ``--ratio``, ``--fs`` [Hz],
        ``--periods``, ``--period`` [s], ``--freqs`` [Hz], ``--loop``, ``--method``,
        ``--fit-threshold`` [%], ``--max-iterations``, ``--max-amplitude``, ``--resonance``.
    plots : bool
        Write the PNG plots (the CLI's ``--no-plots`` is False).
    growth, pace, settle_s, axis
        Amplitude factor per round, streaming pace (``"real"``/``"fast"``), longest rest
        between runs [s], the logs' ``axis`` name (:class:`~servobench.bench.procedure.sidbe.SidbeOptions`).
    progress : callable(round, done, total), optional
        Streaming progress per round.
    note : callable(str), optional
        Called with each note the CLI prints on stderr before streaming: the default cycle
        rate lowered to fit the drive's link, closed loop chosen for the drive.

    Raises
    ------
    UsageError
        Bad options, a run folder holding an earlier run.
    IdentificationError
        No round produced a model (the axis never moved above the noise); a note says
        where the logs are.
    DriveError
        The drive faulted or dropped the link (the axis was stopped).
    """
    from servobench.bench.procedure.run_folder import check_run_folder, default_out_dir
    from servobench.bench.procedure.sidbe import loop_note, rate_note, run_sidbe
    from servobench.bench.run.runner import default_pace
    from servobench.drivers.registry import open_drive

    options = SidbeOptions(
        amplitude=amplitude, ratio=ratio, fs_hz=fs_hz, periods=periods, period_s=period_s,
        freqs_hz=None if freqs_hz is None else tuple(float(f) for f in freqs_hz), loop=loop, method=method,
        fit_threshold=fit_threshold, max_iterations=max_iterations, growth=growth,
        max_amplitude=max_amplitude, pace=pace, settle_s=settle_s, resonance=resonance, plots=plots,
        axis=axis,
    )  # fmt: skip
    options.validate()
    out_dir = Path(out) if out is not None else default_out_dir()
    check_run_folder(out_dir)  # before the drive is even opened
    if isinstance(drive, str):
        drive = open_drive(drive)
    options.validate(drive)
    say = note or (lambda _text: None)
    if text := rate_note(fs_hz, drive):
        say(text)
    try:
        with drive if not drive.is_open else contextlib.nullcontext(drive):  # closed again if opened here
            if text := loop_note(options, drive):
                say(text)
            sr = run_sidbe(drive, options, out_dir, progress=progress)
    except IdentificationError as err:  # no model: say where the logs of the rounds are
        add_note(err, f"no model.json written; the logs are kept in {out_dir}")
        raise
    return SidbeResult(
        model=load_model(sr.model_path),
        verdict=sr.verdict,
        log=sr.log_path,
        fit_percent=float(sr.result.fit_percent),
        fit_threshold=float(sr.fit_threshold),
        out_dir=sr.out_dir,
        model_file=sr.model_path,
        plots=tuple(sr.plots),
        iterations=tuple(sr.iterations),
        headline=sr.headline(),
        pace=pace or drive.url.get_str("pace", "") or default_pace(drive),
        link_max_hz=drive.max_rate_hz(),
        details=sr,
        _json=plain(sr.to_json()),
    )


# ---------------------------------------------------------------------------- commission
@dataclass(frozen=True)
class CommissionResult:
    """A commissioning record, as ``servobench commission`` leaves it.

    Attributes
    ----------
    status : {"complete", "failed", "dry-run"}
    verdict : Verdict or None
        The record's verdict (PASS, PASS with remarks, FAIL); None after a dry run.
    out_dir : Path
        The record folder (``model.json``, ``log.csv``, ``report.html``, ``commission.json`` ...).
    model : Model or None
        The record's ``model.json`` (with the feed-forward, the PI and the values to program);
        None after a dry run.
    """

    status: str
    verdict: Verdict | None
    out_dir: Path
    model: Model | None
    _json: Mapping[str, Any] = field(default_factory=dict, repr=False, compare=False)

    def to_dict(self) -> dict[str, Any]:
        """``commission.json``: the verdict, how far it got, the steps, the files."""
        return plain(self._json)


def commission(
    drive: str,
    *,
    config: PathLike | None = None,
    out: PathLike | None = None,
    yes: bool = False,
    dry_run: bool = False,
    record_bus: PathLike | None = None,
) -> CommissionResult:
    """Commission the drive at URL ``drive``, as ``servobench commission``.

    Parameters
    ----------
    drive : str
        The drive URL (its limit keys count as limits).
    config : path, optional
        The commissioning config (TOML, see ``examples/bench.toml``).
    out : path, optional
        The record folder (default ``commission-<date>-<time>``).
    yes : bool
        No questions: the limits from ``config`` (all required), one fault reset attempted.
    dry_run : bool
        Read only: check and confirm, then say what would be done.
    record_bus : path, optional
        Record the raw bus traffic here, on transports that can.

    Raises
    ------
    CommissionRefused
        The axis is not safe or not fit to identify (a :class:`ServobenchError`).
    UsageError, DriveError
    """
    from servobench.bench.commission.config import load_config
    from servobench.bench.commission.record import MODEL_FILE, STATUS_FILE
    from servobench.bench.commission.sequence import CommissionOptions
    from servobench.bench.commission.sequence import commission as run_commission

    out_dir = Path(out) if out is not None else Path(time.strftime("commission-%Y%m%d-%H%M%S"))
    options = CommissionOptions(
        drive_url=drive,
        config=load_config(config),
        out_dir=out_dir,
        assume_yes=yes,
        dry_run=dry_run,
        record_bus=Path(record_bus) if record_bus is not None else None,
    )
    result = run_commission(options)
    status = json.loads((out_dir / STATUS_FILE).read_text(encoding="utf-8"))
    done = result.status != "dry-run"
    return CommissionResult(
        status=result.status,
        verdict=Verdict(result.verdict) if done else None,
        out_dir=result.out_dir,
        model=load_model(out_dir / MODEL_FILE) if done else None,
        _json=status,
    )


# ---------------------------------------------------------------------------- fleet
@dataclass(frozen=True)
class FleetResult:
    """A fleet's logs re-identified and trended per axis, as ``servobench fleet``.

    Attributes
    ----------
    rows : tuple of FleetRow
        One per log: axis, time, model, fit, effects, or the error.
    axes : tuple of AxisTrend
        Each axis over time: drift of each parameter [%], flagged or not and why.
    out_dir : Path
        Holds ``fleet.csv``, ``fleet.parquet`` and ``trend.html``.
    page : Path
        ``trend.html``.
    """

    rows: tuple[FleetRow, ...]
    axes: tuple[AxisTrend, ...]
    out_dir: Path
    page: Path

    @property
    def failed(self) -> tuple[FleetRow, ...]:
        """The rows of the logs that could not be processed."""
        return tuple(r for r in self.rows if not r.ok)

    @property
    def flagged(self) -> tuple[AxisTrend, ...]:
        return tuple(t for t in self.axes if t.flagged)

    def to_dict(self) -> dict[str, Any]:
        """The object ``servobench fleet --json`` prints: ``logs``, ``failed``, ``axes``."""
        doc = {"logs": len(self.rows), "failed": len(self.failed), "axes": [t.to_json() for t in self.axes]}
        return plain(doc, allow_nan=False)


def fleet(
    logs: PathLike | Iterable[PathLike],
    out: PathLike,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    diagnose: bool = False,
    threshold_percent: float | None = None,
    progress: Callable[[int, int], None] | None = None,
    note: Callable[[str], None] | None = None,
) -> FleetResult:
    """Re-identify a fleet's logs on Dask and trend each axis, as ``servobench fleet``.

    Parameters
    ----------
    logs : path or iterable of paths
        CSV logs, or folders searched for them.
    out : path
        Folder for ``fleet.csv``, ``fleet.parquet`` and ``trend.html``.
    workers : int, optional
        Processes of a local Dask cluster (default one per core).
    scheduler : str, optional
        Run on an existing Dask scheduler instead, e.g. ``tcp://host:8786``.
    diagnose : bool
        Also diagnose every log.
    threshold_percent : float, optional
        Drift of a Coulomb level or B that flags an axis [%] (``--threshold``).
    progress : callable(done, total), optional
        Called with ``(0, total)`` once the cluster is up, then as the logs are done.
    note : callable(str), optional
        Called once the cluster is up, with how many logs run on how many workers of which
        scheduler (the line the CLI prints on stderr).

    Raises
    ------
    FleetEngineError
        Dask or pyarrow missing (the ``fleet`` extra), a cluster that cannot be reached.
    UsageError
    KeyboardInterrupt
        Ctrl-C: the cluster is shut down. During the jobs or the figures a ``FleetInterrupted``,
        after the rows done so far were written (a note says where); while the page is
        written, with a note saying so.
    """
    from servobench.bench.fleet.engine import (
        FleetInterrupted,
        connect,
        map_on,
        require_fleet_extra,
        run_on,
        worker_count,
    )
    from servobench.bench.fleet.page import axis_figure, write_page
    from servobench.bench.fleet.sources import find_logs
    from servobench.bench.fleet.table import CSV_FILE, PARQUET_FILE, write_csv, write_parquet
    from servobench.bench.fleet.trend import DEFAULT_THRESHOLD_PERCENT, axis_trends

    threshold = DEFAULT_THRESHOLD_PERCENT if threshold_percent is None else threshold_percent
    require_fleet_extra()
    axis_trends([], threshold)  # checks the threshold before any work
    if workers is not None and workers < 1:
        raise UsageError(f"--workers must be >= 1, got {workers}")
    out_dir = Path(out)
    if out_dir.exists() and not out_dir.is_dir():
        raise UsageError(f"--out {out_dir} is a file; name a folder")
    sources = find_logs([logs] if isinstance(logs, (str, os.PathLike)) else logs)
    out_dir.mkdir(parents=True, exist_ok=True)

    def tables(rows: Sequence[FleetRow]) -> None:
        write_csv(rows, out_dir / CSV_FILE)
        write_parquet(rows, out_dir / PARQUET_FILE)

    def kept(stop: FleetInterrupted) -> FleetInterrupted:
        tables(stop.rows)
        done = sum(1 for r in stop.rows if not r.error.startswith("not processed"))
        add_note(stop, f"{done} of {len(sources)} logs done, kept in {out_dir / CSV_FILE}")
        return stop

    with connect(workers, scheduler) as client:
        if note is not None:
            address = client.scheduler.address
            where = "in this process" if address.startswith("inproc://") else f"scheduler {address}"
            note(f"{len(sources)} logs on {worker_count(client)} Dask workers ({where})")
        if progress is not None:
            progress(0, len(sources))
        try:
            rows = run_on(client, sources, diagnose, progress)
        except FleetInterrupted as stop:
            raise kept(stop) from None
        tables(rows)
        trends = axis_trends(rows, threshold)
        try:
            figures = map_on(client, axis_figure, trends, threshold_percent=threshold)
        except KeyboardInterrupt:
            raise kept(FleetInterrupted(rows)) from None
    try:
        page = write_page(rows, trends, threshold, out_dir, figures)
    except KeyboardInterrupt as err:
        add_note(err, f"interrupted while writing {out_dir}; run fleet again")
        raise
    return FleetResult(tuple(rows), tuple(trends), out_dir, page)
