"""The whole SIDBE procedure on a drive, including the paper's step 6.

1. Design the periodic binary excitation ``u1`` and ``u2 = ratio * u1``
   (:mod:`servobench.bench.procedure.excitation`).
2.-3. Apply both to the drive and log them (:func:`servobench.bench.run.runner.stream_runs`).
4.-5. Identify the model (:func:`servobench.bench.identify.auto.identify`: SIDBE and/or the
   joint estimator) and verify it by simulation.
6. When the verification fit falls short of ``fit_threshold`` (or the data
   cannot yield a model, e.g. the axis did not break away), raise the
   amplitude by ``growth`` up to the drive's limit; once at the limit,
   redesign the spectrum around the identified corner frequency
   ``B / (2 pi M)``; then run again, at most ``max_iterations`` times.

An axis with limited travel (``xmin``/``xmax`` of the drive, ``loop =
auto``, the default) is excited in closed loop instead
(:mod:`servobench.bench.procedure.closed_rounds`): a hold loop keeps it inside its
window, the excitation is designed to fit, and step 6 raises the amplitude
only while the measured travel still fits. So is any axis of a drive that
takes a command only under its own position hold (:attr:`Drive.hold_only`:
a CiA 402 drive without cyclic synchronous torque, or told ``mode=csp``),
window or not (:func:`loop_note` says so).

The run folder (:mod:`servobench.bench.procedure.run_folder`): each round streams to
``log-<i>.csv`` as its samples arrive; the round whose model is accepted is
copied to ``log.csv``, the log ``model.json`` describes. A folder that
already holds a run is refused, never overwritten.

Public API (``commission`` builds on it): :class:`SidbeOptions`,
:class:`Iteration`, :class:`SidbeResult`, :func:`run_sidbe`,
:func:`check_run_folder`, :func:`loop_note`, :func:`rate_note`.
"""

from __future__ import annotations

import json
import math
import shutil
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any

from servobench.bench.blas_threads import on_one_blas_thread
from servobench.bench.identify.auto import METHODS, identify
from servobench.bench.log.io import read_log
from servobench.bench.model.servo import IdentificationResult, ServoModel
from servobench.bench.procedure import excitation as exc
from servobench.bench.procedure.closed_rounds import closed_rounds
from servobench.bench.procedure.run_folder import (
    LOG_FILE,
    MODEL_FILE,
    check_run_folder,
    describe_files,
    round_log_name,
)
from servobench.bench.run.runner import DEFAULT_SETTLE_S, stream_runs
from servobench.bench.run.travel import TravelWindow
from servobench.drivers.base import Drive, Limits
from servobench.errors import IdentificationError, UsageError
from servobench.verdict import Verdict

#: Default verification fit that ends the procedure [%].
DEFAULT_FIT_THRESHOLD = 90.0
#: Default number of excite-identify rounds.
DEFAULT_MAX_ITERATIONS = 4
#: Default amplitude growth per round.
DEFAULT_GROWTH = 2.0
#: Without a drive limit (max_u), the amplitude may grow to this multiple of the first.
UNLIMITED_GROWTH_CAP = 8.0
#: Choices of ``--loop``: ``auto`` closes the loop whenever the travel is finite.
LOOPS = ("auto", "open", "closed")

Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class SidbeOptions:
    """Options of :func:`run_sidbe` (frequencies in Hz, amplitudes in command units).

    Attributes
    ----------
    amplitude, ratio, fs_hz, periods, period_s, freqs_hz
        The excitation (see :func:`servobench.bench.procedure.excitation.make_design`); ``freqs_hz``
        None means log-spaced default lines; ``fs_hz`` None means the drive's
        link decides (:meth:`for_drive`). ``amplitude`` None means the default: 1
        in open loop, chosen to fit the travel in closed loop.
    loop : {"auto", "open", "closed"}
        Excite in open loop, or in closed loop under a hold loop; ``auto``
        closes the loop whenever the drive's travel (``xmin``/``xmax``) is finite,
        and on a drive that takes a command only under its own hold (always).
    method : {"auto", "sidbe", "joint"}
    fit_threshold : float
        Verification fit [%] that ends the procedure.
    max_iterations : int
        Most excite-identify rounds (1 disables step 6).
    growth : float
        Amplitude factor per round (> 1).
    max_amplitude : float or None
        Highest amplitude step 6 may use; default the drive's ``max_u``, or
        ``8 * amplitude`` when the drive sets none.
    pace : {"real", "fast"} or None
        Streaming pace (default: the drive's).
    settle_s : float
        Longest rest between runs [s].
    resonance : bool
        Let SIDBE fit a series resonance.
    plots : bool
        Write PNG plots.
    axis : str
        The logs' ``# axis`` line (``servobench fleet`` groups records by it);
        "" names the axis by the drive URL's address.
    """

    amplitude: float | None = None
    ratio: float = exc.DEFAULT_RATIO
    fs_hz: float | None = None
    periods: int = exc.DEFAULT_PERIODS
    period_s: float = exc.DEFAULT_PERIOD_S
    freqs_hz: tuple[float, ...] | None = None
    loop: str = "auto"
    method: str = "auto"
    fit_threshold: float = DEFAULT_FIT_THRESHOLD
    max_iterations: int = DEFAULT_MAX_ITERATIONS
    growth: float = DEFAULT_GROWTH
    max_amplitude: float | None = None
    pace: str | None = None
    settle_s: float = DEFAULT_SETTLE_S
    resonance: bool = False
    plots: bool = True
    axis: str = ""

    def design(self) -> exc.ExcitationDesign:
        """The first round's excitation (validates the options)."""
        return exc.make_design(
            exc.DEFAULT_AMPLITUDE if self.amplitude is None else self.amplitude,
            ratio=self.ratio,
            fs_hz=exc.DEFAULT_FS_HZ if self.fs_hz is None else self.fs_hz,
            periods=self.periods,
            period_s=self.period_s,
            freqs_hz=self.freqs_hz,
        )

    def for_drive(self, drive: Drive) -> SidbeOptions:
        """These options at the cycle rate ``drive``'s link carries.

        ``fs_hz`` None: the link's default (:func:`servobench.drivers.link_budget.default_rate_hz`);
        an ``fs_hz`` beyond :meth:`Drive.max_rate_hz` raises :class:`UsageError` naming the limit.
        """
        from servobench.drivers.link_budget import drive_rate_hz

        return replace(self, fs_hz=drive_rate_hz(self.fs_hz, drive, exc.DEFAULT_FS_HZ))

    def validate(self, drive: Drive | None = None) -> exc.ExcitationDesign:
        """Raise :class:`UsageError` for bad options (a rate beyond the drive's link, an
        amplitude beyond its ``max_u``); the design at the rate the drive's link carries."""
        design = (self if drive is None else self.for_drive(drive)).design()
        if self.method not in METHODS:
            raise UsageError(f"unknown method {self.method!r}; choose from {', '.join(METHODS)}")
        if self.loop not in LOOPS:
            raise UsageError(f"unknown loop {self.loop!r}; choose from {', '.join(LOOPS)}")
        if not (int(self.max_iterations) == self.max_iterations and self.max_iterations >= 1):
            raise UsageError("max_iterations must be an integer >= 1")
        if not (math.isfinite(self.growth) and self.growth > 1):
            raise UsageError("growth must be > 1")
        if not math.isfinite(self.fit_threshold) or self.fit_threshold > 100:
            raise UsageError("fit threshold must be a number <= 100 %")
        if drive is not None and drive.hold_only and self.loop == "open":
            raise UsageError(
                f"--loop open cannot excite this {drive.url.scheme} drive: it takes a command only as "
                "the torque offset of its own position hold; use --loop auto (or closed)"
            )
        # without an amplitude, closed loop chooses one within the limits: nothing to check
        chosen = self.amplitude is None and (
            self.loop == "closed" or (drive is not None and self.closed(drive))
        )
        if drive is not None and not chosen and design.amplitude > drive.limits.max_command:
            raise UsageError(
                f"amplitude {design.amplitude:g} exceeds the drive limit max_u = {drive.limits.max_command:g}"
            )
        if self.max_amplitude is not None and not chosen and not self.max_amplitude >= design.amplitude:
            raise UsageError("max amplitude must be >= amplitude")
        return design

    def amplitude_cap(self, drive: Drive, start: float | None = None) -> float:
        """Highest amplitude step 6 may reach on ``drive`` (``start``: the first round's amplitude)."""
        limit = drive.limits.max_command
        cap = self.max_amplitude
        if cap is None:
            first = start if start is not None else self.design().amplitude
            cap = limit if math.isfinite(limit) else UNLIMITED_GROWTH_CAP * first
        return min(cap, limit)

    def closed(self, drive: Drive | Limits) -> bool:
        """Whether to excite in closed loop on ``drive`` (or on a drive with these limits): on
        an open :attr:`~Drive.hold_only` drive unless ``loop = open`` (which :meth:`validate`
        refuses), else with ``loop = auto`` where the travel is finite."""
        if isinstance(drive, Drive) and drive.hold_only:
            return self.loop != "open"  # open: refused by validate()
        if self.loop == "auto":
            return TravelWindow.of(drive if isinstance(drive, Limits) else drive.limits).finite
        return self.loop == "closed"


def loop_note(options: SidbeOptions, drive: Drive) -> str:
    """One line for the terminal when closed loop was chosen for the drive, not for its travel
    (a :attr:`~Drive.hold_only` drive with ``loop = auto``); ``""`` otherwise."""
    if not drive.hold_only or options.loop != "auto":
        return ""
    window = TravelWindow.of(drive.limits)
    where = "inside xmin/xmax" if window.finite else "near where it stands (no xmin/xmax needed)"
    return (
        f"closed loop: the {drive.url.scheme} drive takes a command only as the torque offset of its "
        f"own position hold, so the excitation runs under that hold, {where}"
    )


def rate_note(requested_hz: float | None, drive: Drive) -> str:
    """One line for the terminal when the default cycle rate was lowered to fit the drive's
    link (no rate requested); ``""`` otherwise."""
    if requested_hz is not None:
        return ""
    from servobench.drivers.link_budget import drive_rate_hz, lowered_rate_note

    chosen = drive_rate_hz(None, drive, exc.DEFAULT_FS_HZ)
    return lowered_rate_note(None, chosen, drive, exc.DEFAULT_FS_HZ)


@dataclass(frozen=True)
class Iteration:
    """One excite-identify round: what was applied, how well the model fitted, what came next."""

    index: int
    amplitude: float
    freqs_hz: tuple[float, ...]
    fit_percent: float | None
    method: str | None
    log_path: Path
    action: str
    error: str = ""
    travel_share: float | None = None

    def as_dict(self) -> dict[str, Any]:
        out = {
            "index": self.index,
            "amplitude": self.amplitude,
            "freqs": list(self.freqs_hz),
            "fit_percent": self.fit_percent,
            "method": self.method,
            "log": str(self.log_path),
            "action": self.action,
            "error": self.error,
        }
        if self.travel_share is not None:  # closed loop: share of the room the round used
            out["travel_share"] = self.travel_share
        return out


@dataclass(frozen=True)
class SidbeResult:
    """Outcome of :func:`run_sidbe`.

    Attributes
    ----------
    result : IdentificationResult
        The accepted (or, when the threshold was never met, the best) model.
    iterations : tuple of Iteration
    design : ExcitationDesign
        The excitation of the accepted round.
    passed : bool
        The verification fit reached the threshold.
    fit_threshold : float
    out_dir, log_path, model_path : Path
    plots : tuple of Path
    hold : mapping or None
        Closed loop: where the hold loop ran, its parameters, the travel room and
        the share of it used, and what the probe learnt; None in open loop.
    accepted_log : Path or None
        The round's log that ``log_path`` copies.
    fs_achieved_hz : float
        Cycle rate the host achieved streaming the accepted round [Hz].
    """

    result: IdentificationResult
    iterations: tuple[Iteration, ...]
    design: exc.ExcitationDesign
    passed: bool
    fit_threshold: float
    out_dir: Path
    log_path: Path
    model_path: Path
    plots: tuple[Path, ...] = field(default_factory=tuple)
    hold: Mapping[str, Any] | None = None
    accepted_log: Path | None = None
    fs_achieved_hz: float = math.nan
    #: The drive's scale factors the log states (``drive_scale`` of model.json), empty when none.
    drive_scale: Mapping[str, Any] = field(default_factory=dict)
    #: What the drive did otherwise than asked during the run (:attr:`Drive.remarks`: an optional
    #: object refused, a stop by disable voltage), for model.json and the summary; empty when none.
    remarks: tuple[str, ...] = ()

    @property
    def loop(self) -> str:
        return "open" if self.hold is None else "closed"

    @property
    def verdict(self) -> Verdict:
        """PASS when the verification fit reached the threshold and the run's timing figure keeps
        the model within its stated accuracy; PASS with remarks when the fit reached it but the
        figure does not (the model fits its own log, yet its parameters may be off by more than
        stated: a host stalled for 10-60 ms gave M 45 % off under a 98.3 % fit); FAIL below it."""
        timing = self.result.timing
        return Verdict.of(self.passed, remarks=timing is not None and not timing.within_accuracy)

    def to_json(self) -> dict[str, Any]:
        """``verdict`` (:attr:`verdict`'s word: ``"pass"``, ``"pass with remarks"`` or ``"fail"``)
        first, then the model keys of :meth:`IdentificationResult.to_json` and the procedure."""
        out = {"verdict": self.verdict.word, **self.result.to_json()}
        d = self.design
        out.update(
            {
                "amplitude": d.amplitude,
                "ratio": d.ratio,
                "fs": d.fs_hz,
                "fs_achieved": self.fs_achieved_hz if math.isfinite(self.fs_achieved_hz) else None,
                "periods": d.periods,
                "samples_per_period": d.samples_per_period,
                "freqs": list(d.freqs_hz),
                "iterations": [it.as_dict() for it in self.iterations],
                "verification": {
                    "fit_percent": out["fit_percent"],
                    "threshold": self.fit_threshold,
                    "passed": self.passed,
                },
                "out_dir": str(self.out_dir),
                "log": str(self.log_path),
                "model_file": str(self.model_path),
                "plots": [str(p) for p in self.plots],
                "loop": self.loop,
                "files": self.files(),
            }
        )
        if self.hold is not None:  # no window: the room is unbounded, null in JSON
            out["hold"] = {k: None if isinstance(v, float) and math.isinf(v) else v
                           for k, v in self.hold.items()}  # fmt: skip
        if self.drive_scale:
            out["drive_scale"] = dict(self.drive_scale)
        if self.remarks:
            out["remarks"] = list(self.remarks)
        return out

    def headline(self) -> str:
        """The verdict line: the verification fit against the threshold, and what to do on a fail."""
        fit, threshold = self.result.fit_percent, self.fit_threshold
        verdict = self.verdict
        if verdict is Verdict.REMARKS:
            t = self.result.timing
            why = (f"the parameters may be off by up to {t.model_error_bound_pct:.2g} % against the stated "
                   f"{t.accuracy_pct:g} %" if t.delay_separable
                   else "the drive's action delay cannot be told from the plant's lag")  # fmt: skip
            return verdict.line(f"SIDBE verification fit {fit:.2f} % >= threshold {threshold:g} %, but the "
                                f"run's timing says {why} (the WARNING below says what to change)")  # fmt: skip
        if self.passed:
            return Verdict.PASS.line(f"SIDBE verification fit {fit:.2f} % >= threshold {threshold:g} %")
        return Verdict.FAIL.line(
            f"SIDBE verification fit {fit:.2f} % < threshold {threshold:g} %; do not use this model before "
            f"the cause is found (servobench diagnose {self.log_path} names what the model lacks)"
        )

    def files(self) -> dict[str, str]:
        """What each log of the run folder holds (``model.json``'s ``files`` object)."""
        return describe_files(self.out_dir, self.accepted_log, self.iterations, closed=self.hold is not None)


@on_one_blas_thread
def run_sidbe(
    drive: Drive,
    options: SidbeOptions,
    out_dir: str | Path,
    progress: Callable[[int, int, int], None] | None = None,
    known: ServoModel | None = None,
) -> SidbeResult:
    """Run the SIDBE procedure on ``drive`` and write ``out_dir/log.csv``, ``model.json`` and plots.

    Parameters
    ----------
    drive : Drive
        Opened here if it is not open yet (and then closed again).
    options : SidbeOptions
    out_dir : path
        Created if missing; refused when it holds an earlier run
        (:func:`check_run_folder`). Each round logs ``log-<i>.csv``; the
        accepted one is copied to ``log.csv``.
    progress : callable(iteration, done, total), optional
        Streaming progress, samples done of total, per round.
    known : ServoModel, optional
        Closed loop: what is known of the axis already (from a bump test); without
        it a relay probe learns it first (``probe.csv``).

    Raises
    ------
    UsageError
        Bad options. Drive errors propagate (the runner has stopped the axis).
    IdentificationError
        No round produced a model.
    """
    options = options.for_drive(drive)
    design = options.validate(drive)
    out = Path(out_dir)
    check_run_folder(out)
    out.mkdir(parents=True, exist_ok=True)
    opened_here = not drive.is_open
    if opened_here:
        drive.open()
    hold = None
    try:
        if opened_here and drive.hold_only:  # known only now: refuse --loop open on it
            options.validate(drive)
        if options.closed(drive):
            iterations, best, hold = closed_rounds(drive, options, out, progress, known, Iteration)
        else:
            cap = options.amplitude_cap(drive)
            iterations, best = _rounds(drive, options, design, cap, out, progress)
    finally:
        remarks = tuple(drive.remarks)
        if opened_here:
            drive.close()
    if best is None:
        errors = "; ".join(f"round {it.index}: {it.error}" for it in iterations if it.error)
        raise IdentificationError(f"no round produced a model ({errors})")
    result, best_design, best_log, achieved_hz = best
    log_path = out / LOG_FILE
    shutil.copyfile(best_log, log_path)
    passed = result.fit_percent >= options.fit_threshold
    plots: tuple[Path, ...] = ()
    if options.plots:
        from servobench.bench.report.plots import write_plots

        plots = tuple(write_plots(result, out))
    model_path = out / MODEL_FILE
    from servobench.bench.model.program import drive_scale_json

    sr = SidbeResult(
        result,
        tuple(iterations),
        best_design,
        passed,
        options.fit_threshold,
        out,
        log_path,
        model_path,
        plots,
        hold,
        best_log,
        achieved_hz,
        drive_scale_json(read_log(log_path).metadata, str(log_path)),
        remarks,
    )
    model_path.write_text(json.dumps(sr.to_json(), indent=2) + "\n", encoding="utf-8")
    return sr


def _rounds(drive, options, design, cap, out, progress):
    iterations: list[Iteration] = []
    best: tuple[IdentificationResult, exc.ExcitationDesign, Path, float] | None = None
    redesigned = options.freqs_hz is not None
    for index in range(1, int(options.max_iterations) + 1):
        log_path = out / round_log_name(index)
        excitation = exc.design_excitation(design)
        meta = {**design.metadata(), "loop": "open", "iteration": index}
        if options.axis:
            meta["axis"] = options.axis

        def tick(done: int, total: int, _i: int = index) -> None:
            if progress is not None:
                progress(_i, done, total)

        streamed = stream_runs(
            drive,
            excitation.runs(),
            design.fs_hz,
            log_path,
            metadata=meta,
            pace=options.pace,
            settle_s=options.settle_s,
            progress=tick,
        )
        result: IdentificationResult | None = None
        error = ""
        try:
            result = identify(read_log(log_path), options.method, resonance=options.resonance)
        except IdentificationError as err:
            error = str(err)
        fit = None if result is None else result.fit_percent
        if result is not None and (best is None or result.fit_percent > best[0].fit_percent):
            best = (result, design, log_path, streamed.fs_achieved_hz)
        method = None if result is None else result.method
        this_round = partial(Iteration, index, design.amplitude, design.freqs_hz, fit, method, log_path)
        if fit is not None and fit >= options.fit_threshold:
            iterations.append(this_round("accepted", error))
            break
        last = index == options.max_iterations
        if design.amplitude < cap:
            new_amp = min(design.amplitude * options.growth, cap)
            action = f"fit below threshold: amplitude raised to {new_amp:g}"
            next_design = design.with_amplitude(new_amp)
        elif not redesigned and result is not None:
            corner = result.model.B / (2 * math.pi * result.model.M)
            freqs = exc.freqs_around(corner, design.fs_hz, design.samples_per_period)
            action = (
                f"fit below threshold at the amplitude limit: spectrum redesigned to "
                f"{freqs[0]:.3g}-{freqs[-1]:.3g} Hz (identified corner {corner:.3g} Hz)"
            )
            next_design = design.with_freqs(freqs)
            redesigned = True
        else:
            iterations.append(this_round("stopped: threshold not reached within the drive limits", error))
            break
        iterations.append(this_round("stopped: iteration limit reached" if last else action, error))
        design = replace(next_design)
    return iterations, best
