"""The commissioning steps, in order, Ctrl-C safe.

1. link and drive: identity, firmware, state, faults (one reset), feedback;
2. limits: confirmed at the terminal or taken from the config under ``--yes``,
   then put into the drive URL so the Drive layer enforces them;
3. bump test;
4. SIDBE with its verification loop, then the diagnosis;
5. design (friction feed-forward, velocity PI), simulation check, record and report.

Step 1 runs on a connection opened with the URL as given (under ``--dry-run``
opened read-only, :meth:`~servobench.drivers.base.Drive.open`: nothing is
written to the drive on any transport); the moving steps run on a second
connection opened with the confirmed limits.
Every connection is a context manager, so on any exit -- refusal, error,
Ctrl-C -- the axis is stopped and disabled; logs are written as samples
arrive and kept, and ``commission.json`` records how far it got.
``--dry-run`` stops after step 2 and says what the rest would do.

A commissioning that runs to the end has one verdict, the banner of
``report.html`` (:func:`servobench.bench.report.commission_record.verdict`):
the terminal's last line is that banner, ``commission.json`` carries its word
as ``verdict`` (first key; ``status`` "complete" for a pass, "failed" for a
fail) and the command's exit status follows it. When the diagnosis names an
effect that closes the velocity gap, the values to program come from the
diagnosed model (:mod:`.source`), and the record says so.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

from servobench.bench.blas_threads import on_one_blas_thread
from servobench.bench.commission import integration
from servobench.bench.commission.bump import BumpResult, at_link_rate, plan_text, run_bump_test
from servobench.bench.commission.checks import DriveCheck, check_drive
from servobench.bench.commission.closedloop import check_compensation, reference_amplitude
from servobench.bench.commission.config import CommissionConfig, LimitSettings
from servobench.bench.commission.design import design_pi, friction_feed_forward
from servobench.bench.commission.errors import CommissionRefused
from servobench.bench.commission.limits import (
    ConfirmedLimits,
    TerminalPrompter,
    confirm_at_terminal,
    limits_from_config,
    merge_limits,
    url_with_limits,
)
from servobench.bench.commission.record import (
    MAT_FILE,
    MODEL_FILE,
    STATUS_FILE,
    Design,
    Progress,
    identity_record,
    model_record,
    write_json,
    write_mat,
)
from servobench.bench.commission.source import DIAGNOSE, ProgramSource, choose_source
from servobench.bench.commission.ui import Console
from servobench.bench.log.identity import configured_axis
from servobench.bench.log.io import read_log
from servobench.bench.model.program import (
    DriveScale,
    integral_unit,
    loop_delay_cycles,
    program_values,
)
from servobench.bench.model.servo import IdentificationResult, ServoModel
from servobench.bench.report import commission_record as document
from servobench.bench.report.html import REPORT_FILE, write_report
from servobench.drivers.base import Drive
from servobench.drivers.url import parse_drive_url
from servobench.errors import (
    DriveError,
    DriveUnavailableError,
    LimitExceededError,
    UsageError,
    add_note,
)

BUMP_LOG = "bump.csv"
DIAGNOSE_DIR = "diagnose"


@dataclass(frozen=True)
class CommissionOptions:
    """What the technician asked for.

    Attributes
    ----------
    drive_url : str
        The drive URL as given (its own limit keys, if any, count as limits too).
    config : CommissionConfig
    out_dir : Path
        The commissioning record folder (created; must not hold a previous record).
    assume_yes : bool
        Take the limits from the config and reset a fault without asking.
    dry_run : bool
        Read only: no enable, no command; say what would be done.
    record_bus : Path or None
        Raw bus traffic file (python-can formats by suffix).
    """

    drive_url: str
    config: CommissionConfig
    out_dir: Path
    assume_yes: bool = False
    dry_run: bool = False
    record_bus: Path | None = None


@dataclass(frozen=True)
class CommissionResult:
    """A finished commissioning: the model, the design and the files written."""

    status: str
    out_dir: Path
    identification: IdentificationResult | None = None
    design: Design | None = None
    #: The record's verdict: ``"pass"``, ``"pass with remarks"`` or ``"fail"`` ("" before the end).
    verdict: str = ""


DriveFactory = Callable[[str], Drive]


def _default_factory(url: str) -> Drive:
    from servobench.drivers.registry import open_drive

    return open_drive(url)


class Commissioning:
    """One commissioning session; :meth:`run` executes the steps.

    Parameters
    ----------
    options : CommissionOptions
    console : Console
    prompter : TerminalPrompter, optional
        Questions at the terminal (limits, fault reset); needed without ``--yes``.
    drive_factory : callable(url) -> Drive
        Creates (not opens) a drive; :func:`servobench.drivers.registry.open_drive` by default.
    """

    def __init__(
        self,
        options: CommissionOptions,
        console: Console,
        prompter: TerminalPrompter | None = None,
        drive_factory: DriveFactory = _default_factory,
    ) -> None:
        self.o = options
        self.console = console
        self.prompter = prompter
        self.factory = drive_factory
        self.progress = Progress(drive_url=options.drive_url)
        self.out = options.out_dir
        self._t_step = time.monotonic()
        #: The bump settings at the rate the drive's link carries (step 1 sets the rate).
        self.bump = options.config.bump

    # ------------------------------------------------------------------ driver
    def run(self) -> CommissionResult:
        created = not self.out.exists()
        self._prepare_out_dir()
        try:
            result = self._steps()
        except KeyboardInterrupt as err:
            self.progress.status, self.progress.reason = "interrupted", "Ctrl-C"
            add_note(err, self._kept())
            raise
        except CommissionRefused as err:
            self.progress.status, self.progress.reason = "refused", str(err)
            if self.o.dry_run and self._leave_nothing(created):  # read only: nothing behind
                add_note(err, f"nothing was written to {self.out}")
                self.progress.status = "gone"
            raise
        except BaseException as err:
            self.progress.status, self.progress.reason = "error", str(err) or type(err).__name__
            add_note(err, self._kept())
            raise
        finally:
            if self.progress.status != "gone":
                self._keep_files()
                write_json(self.out / STATUS_FILE, self.progress.as_dict())
        return result

    def _leave_nothing(self, created: bool) -> bool:
        """Remove what a refused dry run made: the status file of an earlier dry run or refusal it
        replaces, and the folder when this run created it. False when the folder holds other files."""
        others = [p for p in self.out.iterdir() if p.name != STATUS_FILE] if self.out.is_dir() else []
        if others:
            return False
        (self.out / STATUS_FILE).unlink(missing_ok=True)
        if created:
            self.out.rmdir()
        return True

    def _kept(self) -> str:
        return f"the record so far is kept in {self.out} ({STATUS_FILE} says how far it got)"

    def _prepare_out_dir(self) -> None:
        """Create the record folder; refuse one holding a record (a dry run's or a refusal's
        ``commission.json`` alone is no record: it is replaced)."""
        if (self.out / STATUS_FILE).exists() and not _no_record(self.out):
            raise UsageError(f"{self.out} already holds a commissioning record; choose another --out")
        self.out.mkdir(parents=True, exist_ok=True)

    def _keep_files(self) -> None:
        self.progress.files.extend(
            p.relative_to(self.out).as_posix()
            for p in self.out.rglob("*")
            if p.is_file() and p.name != STATUS_FILE
        )

    def _done(self, step: str, **facts: object) -> None:
        now = time.monotonic()
        self.progress.durations_s[step] = round(now - self._t_step, 3)
        self._t_step = now
        self.progress.steps.append(step)
        self.progress.facts.update(facts)

    # ------------------------------------------------------------------- steps
    def _steps(self) -> CommissionResult:
        config = self.o.config
        settings = merge_limits(config.limits, parse_drive_url(self.o.drive_url))
        preset = limits_from_config(settings) if self.o.assume_yes else None
        check = self._check_step()
        limits, limited_url = self._limits_step(preset or settings, check)
        if self.o.dry_run:
            self._say_plan(limited_url, limits)
            self.progress.status = "dry-run"
            return CommissionResult("dry-run", self.out)
        try:
            bump, sidbe = self._moving_steps(limited_url, limits)
        except LimitExceededError as err:
            raise CommissionRefused(
                f"{err}; the axis was stopped and disabled. Lower the excitation ([sidbe] amplitude, "
                "max_amplitude) or, if the machine allows, confirm a larger max_v or travel"
            ) from err
        diag = self._diagnose_step(sidbe)
        source = self._source(sidbe, diag)
        self.console.step(5, "compensation, PI and the record")
        if source.origin == DIAGNOSE:
            self.console.say(f"the values to program come from {source.description}")
        design = self._design(source.model, limits, sidbe.fs_hz, sidbe.result.units)
        self._done("design")
        banner = self._write_record(check, limits, limited_url, bump, sidbe, diag, design, source)
        word = document.VERDICT_WORDS[banner.status]
        status = "failed" if banner.status == document.FAIL else "complete"
        self.progress.verdict, self.progress.status = word, status
        self.console.say(f"commissioning record in {self.out}")
        self.console.verdict(banner.status, banner.sentence)
        return CommissionResult(status, self.out, sidbe.result, design, word)

    def _source(self, sidbe: integration.SidbeOutcome, diag: integration.DiagnoseOutcome) -> ProgramSource:
        """The model the values to program come from (:mod:`.source`)."""
        ver = sidbe.details.get("verification", {})
        threshold = float(ver.get("threshold", math.nan))
        return choose_source(sidbe.result.model, sidbe.result.fit_percent, threshold, diag.effects,
                             diag.model, diag.gap_before, diag.gap_after, f"{DIAGNOSE_DIR}/{MODEL_FILE}")  # fmt: skip

    def _check_step(self) -> DriveCheck:
        """Step 1 on a read-only connection with the URL as given."""
        self.console.step(1, "link and drive")
        with self._connect(self.o.drive_url, record=self.o.dry_run, read_only=self.o.dry_run) as drive:
            check = check_drive(drive, self.console, dry_run=self.o.dry_run, allow_reset=self._allow_reset)
            self.bump = at_link_rate(self.o.config.bump, self.o.config.sidbe.get("fs_hz"), drive)
        self._done("check", drive_info=check.as_dict())
        return check

    def _limits_step(self, given: ConfirmedLimits | LimitSettings, check: DriveCheck) -> tuple[ConfirmedLimits, str]:
        """Step 2: the confirmed limits and the drive URL that carries them."""
        self.console.step(2, "limits")
        limits = given if isinstance(given, ConfirmedLimits) else self._confirm(given)
        self._check_start_position(limits, check.feedback.position)
        first_pulse = self.o.config.bump.fractions[0] * limits.max_u
        integration.sidbe_options(self.o.config.sidbe, limits.max_u, first_pulse, _finite(limits))  # bad options refuse now
        self.console.ok(f"limits {limits.describe(check.units)} ({limits.how}); enforced by the Drive layer")
        self._done("limits", limits=limits.as_dict())
        return limits, url_with_limits(self.o.drive_url, limits)

    def _moving_steps(self, url: str, limits: ConfirmedLimits) -> tuple[BumpResult, integration.SidbeOutcome]:
        """Steps 3 and 4 on the connection with the limits; closing it stops and disables the axis."""
        c, config = self.console, self.o.config
        with self._connect(url, record=True) as drive:
            if code := drive.fault_code():
                raise CommissionRefused(f"drive reports fault 0x{code:04X} on reconnecting")
            pace = drive.url.get_str("pace", "real") or "real"
            c.step(3, "bump test")
            with c.progress("bump test") as tick:
                bump = run_bump_test(drive, limits, self.bump, self.out / BUMP_LOG, pace=pace, progress=tick)
            u = drive.units.get("u") or "(drive units)"
            c.ok(
                f"moves both ways (at {bump.breakaway_pos:.3g} / -{bump.breakaway_neg:.3g} {u}), "
                "positive command gives positive velocity, feedback consistent"
            )
            self._done("bump", bump=bump.as_dict())

            c.step(4, "SIDBE identification with verification")
            moved_at = max(bump.breakaway_pos, bump.breakaway_neg)
            options = integration.sidbe_options(config.sidbe, limits.max_u, moved_at, _finite(limits))
            options = replace(options, axis=configured_axis(config.identity.machine, config.identity.axis))
            closed = options.closed(drive)
            known = integration.bump_model(bump.log_path) if closed else None
            c.say(f"closed loop: a hold loop keeps the axis in [{limits.xmin:g}, {limits.xmax:g}], the "
                  f"excitation fitted to it ({'from the bump test' if known else 'after a relay probe'})"
                  if closed else f"excitation amplitude {options.amplitude:g} (the verification loop "
                  "may raise it up to max_u)")  # fmt: skip
            with c.progress("SIDBE") as tick:
                sidbe = integration.run_sidbe(drive, options, self.out, tick, known)
        model, unit = sidbe.result.model, sidbe.result.units.parameters()
        ver = sidbe.details.get("verification", {})
        threshold = float(ver.get("threshold", math.nan))
        passed = bool(ver.get("passed", sidbe.result.fit_percent >= threshold))
        say = c.ok if passed else c.warn
        say(
            f"M = {model.M:.5g} {unit['M']}, B = {model.B:.5g} {unit['B']} (pole {model.pole:.4g} {unit['pole']}, "
            f"DC gain {model.dc_gain:.4g} {unit['dc_gain']}), Coulomb +{model.coulomb_pos:.4g} / "
            f"-{model.coulomb_neg:.4g} {unit['coulomb_pos']}, fit {sidbe.result.fit_percent:.1f} % "
            + ("" if passed else f"(below the threshold {threshold:g} %)")
        )
        self._done("sidbe", sidbe=dict(sidbe.details))
        return bump, sidbe

    def _diagnose_step(self, sidbe: integration.SidbeOutcome) -> integration.DiagnoseOutcome:
        self.console.say("diagnosing the model against the log ...")
        diag = integration.diagnose(sidbe.log_path, self.o.config.diagnose, self.out / DIAGNOSE_DIR)
        self.console.ok(
            f"diagnosis: {', '.join(diag.effects) or 'no missing effect'}; "
            f"velocity gap {diag.gap_before:.3g} % -> {diag.gap_after:.3g} %"
        )
        self._done("diagnose", diagnose={"effects": list(diag.effects),
                                         "gap_before": diag.gap_before, "gap_after": diag.gap_after})  # fmt: skip
        return diag

    # ----------------------------------------------------------------- helpers
    def _connect(self, url: str, *, record: bool, read_only: bool = False) -> Drive:
        """The drive at ``url``, open (``read_only``: it writes nothing to the drive, the dry run)."""
        try:
            drive = self.factory(url)
            drive.open(read_only=read_only)
        except DriveError as err:
            raise CommissionRefused(f"cannot connect to the drive: {err}") from err
        if record and self.o.record_bus is not None:
            try:
                drive.record_traffic(str(self.o.record_bus))
                self.console.ok(f"recording bus traffic to {self.o.record_bus}")
            except DriveUnavailableError as err:
                self.console.warn(f"{err}; continuing without a bus recording")
            except BaseException:
                drive.close()
                raise
        return drive

    def _allow_reset(self, code: int) -> bool:
        if self.o.assume_yes:
            return True
        if self.prompter is None:
            return False
        return self.prompter.ask_yes_no(f"Drive in fault 0x{code:04X}. Attempt one fault reset?")

    def _confirm(self, settings) -> ConfirmedLimits:
        if self.prompter is None:
            raise CommissionRefused(
                "the limits must be confirmed: run at a terminal, or pass --yes with every limit "
                "in the [limits] table of --config"
            )
        return confirm_at_terminal(settings, self.prompter)

    @staticmethod
    def _check_start_position(limits: ConfirmedLimits, position: float) -> None:
        if math.isfinite(position) and not limits.xmin <= position <= limits.xmax:
            raise CommissionRefused(
                f"the axis is at {position:.4g}, outside the allowed travel "
                f"[{limits.xmin:g}, {limits.xmax:g}]; move it inside or correct xmin/xmax"
            )

    def _say_plan(self, url: str, limits: ConfirmedLimits) -> None:
        c = self.console
        cfg = self.o.config
        c.step(3, "plan (dry run: nothing is enabled or commanded)")
        c.say(f"would reconnect as {url}")
        c.say("would " + plan_text(limits, self.bump))
        opts = ", ".join(f"{k}={v}" for k, v in cfg.sidbe.items()) or "defaults"
        c.say(f"would run SIDBE with its verification loop ({opts}) and the diagnosis")
        c.say(
            f"would design friction feed-forward and a velocity PI "
            f"(phase margin {cfg.design.phase_margin_deg:g} deg, delay "
            + (f"{cfg.design.delay_cycles:g} cycles)" if cfg.design.delay_cycles is not None
               else "1 cycle plus the identified drive action delay)")
        )
        c.say(f"would write {MODEL_FILE}, log.csv, {BUMP_LOG}, {REPORT_FILE}, {MAT_FILE} in {self.out}")

    def _design(self, model: ServoModel, limits: ConfirmedLimits, fs_hz: float, units) -> Design:
        cfg = self.o.config
        d = cfg.design
        loop_fs = d.fs_hz or fs_hz
        pi = design_pi(model.M, model.B, loop_fs, phase_margin_deg=d.phase_margin_deg,
                       delay_cycles=loop_delay_cycles(model, loop_fs, d.delay_cycles),
                       pi_zero_ratio=d.pi_zero_ratio,
                       max_bandwidth_hz=d.max_bandwidth_hz)  # fmt: skip
        amplitude = reference_amplitude(model.M, model.B, model.coulomb_pos, model.coulomb_neg,
                                        limits.max_u, limits.max_v, cfg.compensation)  # fmt: skip
        ff = friction_feed_forward(model.B, model.coulomb_pos, model.coulomb_neg,
                                   cfg.compensation.sign_band * amplitude)  # fmt: skip
        check = check_compensation(model.M, model.B, model.coulomb_pos, model.coulomb_neg, pi, ff,
                                   limits.max_u, limits.max_v, cfg.compensation)  # fmt: skip
        c, unit, v = self.console, units.parameters(), units.of("v")
        c.ok(f"friction feed-forward: +{ff.coulomb_pos:.4g} / -{ff.coulomb_neg:.4g} {unit['coulomb_pos']}, "
             f"viscous {ff.viscous:.4g} {unit['B']}")  # fmt: skip
        c.ok(
            f"velocity PI: Kp {pi.kp:.4g} {unit['B']}, Ki {pi.ki:.4g} {integral_unit(units)} (crossover "
            f"{pi.crossover_hz:.3g} Hz, phase margin {pi.phase_margin_deg:.1f} deg, gain margin "
            f"{pi.gain_margin_db:.1f} dB)"
        )
        say = c.ok if check.rms_ratio < 1 else c.warn
        say(
            f"simulated tracking error (rms) {check.without_ff.rms_error:.3g} {v} without, "
            f"{check.with_ff.rms_error:.3g} {v} with compensation"
        )
        return Design(ff, pi, check)

    def _write_record(self, check, limits, url, bump, sidbe, diag, design, source) -> document.Verdict:
        """model.json, commission.mat and report.html; the page's verdict."""
        facts = {
            "drive": check.as_dict(),
            "drive_url": url,
            "limits": limits.as_dict(),
            "bump": bump.as_dict(),
            "sidbe": dict(sidbe.details),
            "diagnose": {"effects": list(diag.effects), "gap_before": diag.gap_before,
                         "gap_after": diag.gap_after, **diag.details},  # fmt: skip
            "log": sidbe.log_path.name,
        }
        log = read_log(sidbe.log_path)
        scale = DriveScale.from_metadata(log.metadata, str(sidbe.log_path))
        program = program_values(source.model, design.feed_forward, design.pi, sidbe.result.units, scale)
        who = identity_record(self.o.config.identity, check.info)
        inputs = document.RecordInputs(self.o.config, check, limits, url, bump, sidbe, diag, design, log,
                                       program, scale, self.progress.started, _version(), source)  # fmt: skip
        banner = document.verdict(document.steps(inputs))
        record = model_record(sidbe.result, design, facts, program, who, source.as_dict())
        record["fs"] = sidbe.fs_hz
        if scale.reported:
            record["drive_scale"] = scale.as_json()
        write_json(self.out / MODEL_FILE, {"verdict": document.VERDICT_WORDS[banner.status], **record})
        write_mat(self.out / MAT_FILE, log, sidbe.result, design)
        write_report(self.out / REPORT_FILE, document.page(inputs))
        return banner


def _no_record(out: Path) -> bool:
    """True when ``out`` holds only the ``commission.json`` of a dry run or of a refusal before anything
    was recorded."""
    import json

    if any(p.name != STATUS_FILE for p in out.iterdir()):
        return False
    try:
        status = json.loads((out / STATUS_FILE).read_text(encoding="utf-8")).get("status")
    except (OSError, ValueError, AttributeError):
        return False
    return status in ("dry-run", "refused")


def _finite(limits: ConfirmedLimits) -> bool:
    """Whether the confirmed travel is finite on either side."""
    return math.isfinite(limits.xmin) or math.isfinite(limits.xmax)


def _version() -> str:
    from servobench import __version__

    return __version__


@on_one_blas_thread
def commission(
    options: CommissionOptions,
    console: Console | None = None,
    prompter: TerminalPrompter | None = None,
    drive_factory: DriveFactory = _default_factory,
) -> CommissionResult:
    """Run a commissioning session (see :class:`Commissioning`)."""
    console = console or Console()
    if prompter is None and not options.assume_yes and sys.stdin.isatty():
        prompter = TerminalPrompter(console.rich)
    return Commissioning(options, console, prompter, drive_factory).run()


__all__ = ["CommissionOptions", "CommissionResult", "Commissioning", "commission"]
