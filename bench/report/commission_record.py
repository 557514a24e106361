"""The commissioning record as a page a technician can hand over.

Order, as the reader needs it:

1. the verdict and the identity (site, machine, axis, operator from the
   config; vendor, product, firmware, serial number from the drive);
2. **Summary**: pass, remark or fail per step, and the identified model
   with its 1-sigma uncertainties and units;
3. **Values to program into the drive**: friction feed-forward per
   direction, viscous, PI gains and any filter, in the log's units and in
   the drive's own (:mod:`servobench.bench.model.program`);
4. **Evidence**: drive and limits, bump test, one excitation period,
   velocities, frequency response, friction map, diagnosis, and the
   design's margins and simulation check, every figure captioned.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from servobench.bench.commission.bump import BumpResult
from servobench.bench.commission.checks import DriveCheck, describe_info
from servobench.bench.commission.config import CommissionConfig
from servobench.bench.commission.integration import DiagnoseOutcome, SidbeOutcome
from servobench.bench.commission.limits import ConfirmedLimits
from servobench.bench.commission.record import Design
from servobench.bench.commission.source import DIAGNOSE, ProgramSource
from servobench.bench.log.io import ExperimentLog, read_log
from servobench.bench.model.program import DriveScale, ProgramValue
from servobench.bench.report import commission_figures as figures
from servobench.bench.report import plots
from servobench.bench.report.html import (
    FAIL,
    PASS,
    REMARK,
    Figure,
    Grid,
    KeyValues,
    Section,
    Verdict,
    png_files,
    render,
)
from servobench.bench.report.summary import NO_UNITS, model_rows
from servobench.units import SignalUnits

#: Smallest acceptable gain margin of the PI design [dB] (as the design requires).
MIN_GAIN_MARGIN_DB = 6.0
#: The word of each banner status, as the terminal, ``commission.json`` and the exit status use it.
VERDICT_WORDS = {PASS: "pass", REMARK: "pass with remarks", FAIL: "fail"}
#: Captions of the diagnosis' figures, by file name.
DIAGNOSE_CAPTIONS = {
    "overlay.png": "Measured velocity against the base model and the model with the effects the "
    "diagnosis added.",
    "gap_steps.png": "Velocity gap between simulation and measurement as each effect is added.",
    "residual_spectrum.png": "Spectrum of the velocity residual (measured - simulated), before and "
    "after the added effects.",
    "residual_vs_state.png": "Velocity residual against the state (velocity, position): where the "
    "model misses.",
}


@dataclass(frozen=True)
class RecordInputs:
    """Everything the page shows, gathered by the commissioning sequence."""

    config: CommissionConfig
    check: DriveCheck
    limits: ConfirmedLimits
    url: str
    bump: BumpResult
    sidbe: SidbeOutcome
    diag: DiagnoseOutcome
    design: Design
    log: ExperimentLog
    program: tuple[ProgramValue, ...]
    scale: DriveScale
    started: str
    version: str
    #: The model the values to program come from; the SIDBE model when None.
    source: ProgramSource | None = None

    @property
    def units(self) -> SignalUnits:
        return self.sidbe.result.units


@dataclass(frozen=True)
class Step:
    """One commissioning step's outcome: ``status`` is PASS, REMARK or FAIL."""

    name: str
    status: str
    detail: str


def _bump_step(r: RecordInputs) -> Step:
    b, u = r.bump, r.units.of("u")
    detail = (f"moves both ways (at +{b.breakaway_pos:.3g} / -{b.breakaway_neg:.3g} {u}); "
              "positive command gives positive velocity")  # fmt: skip
    if b.position_checked:
        return Step("Bump test", PASS, detail + "; position agrees with the integrated velocity")
    return Step("Bump test", REMARK, detail + "; the motion was too small to check position against velocity")


def _sidbe_step(r: RecordInputs) -> Step:
    res = r.sidbe.result
    ver = r.sidbe.details.get("verification", {})
    threshold = float(ver.get("threshold", math.nan))
    passed = bool(ver.get("passed", res.fit_percent >= threshold))
    detail = f"verification fit {res.fit_percent:.1f} % (threshold {threshold:g} %), method {res.method}"
    src = r.source
    if src is None or src.origin != DIAGNOSE:
        return Step("Identification (SIDBE)", PASS if passed else FAIL, detail)
    if passed:
        return Step("Identification (SIDBE)", REMARK, f"{detail}; the values to program come from "
                    f"{src.description} (fit {src.fit_percent:.1f} %)")  # fmt: skip
    if src.passed:
        return Step("Identification (SIDBE)", REMARK, f"base {detail}, below it; {src.description}, "
                    f"fits {src.fit_percent:.1f} %: the values to program come from it")  # fmt: skip
    return Step("Identification (SIDBE)", FAIL, f"base {detail}; {src.description}, still only "
                f"{src.fit_percent:.1f} %")  # fmt: skip


def _diagnose_step(r: RecordInputs) -> Step:
    d = r.diag
    if not d.effects:
        return Step("Diagnosis", PASS, f"no missing effect (velocity gap {d.gap_before:.3g} %)")
    return Step("Diagnosis", REMARK, f"the model lacks {', '.join(d.effects)}: with it the velocity gap "
                f"drops from {d.gap_before:.3g} % to {d.gap_after:.3g} %")  # fmt: skip


def _design_steps(r: RecordInputs) -> list[Step]:
    pi, chk = r.design.pi, r.design.check
    target = r.config.design.phase_margin_deg
    ok = pi.phase_margin_deg >= target - 0.5 and pi.gain_margin_db >= MIN_GAIN_MARGIN_DB
    pi_step = Step("Velocity PI design", PASS if ok else FAIL,
                   f"crossover {pi.crossover_hz:.3g} Hz, phase margin {pi.phase_margin_deg:.1f} deg "
                   f"(target {target:g}), gain margin {pi.gain_margin_db:.1f} dB")  # fmt: skip
    v = r.units.of("v")
    detail = (f"rms tracking error {chk.without_ff.rms_error:.3g} {v} with PI alone, "
              f"{chk.with_ff.rms_error:.3g} {v} with the feed-forward (x {chk.rms_ratio:.2f})")  # fmt: skip
    return [pi_step, Step("Friction compensation (simulation)", PASS if chk.rms_ratio < 1 else FAIL, detail)]


def _limits_text(r: RecordInputs) -> str:
    lim, units = r.limits, r.units
    return (f"|u| <= {lim.max_u:g} {units.of('u')}, |v| <= {lim.max_v:g} {units.of('v')}, "
            f"x in [{lim.xmin:g}, {lim.xmax:g}] {units.of('x')}")  # fmt: skip


def steps(r: RecordInputs) -> list[Step]:
    """Pass, remark or fail of every step, in order."""
    c = r.check
    fault = (f"; fault 0x{c.fault_found:04X} found and reset" if c.fault_reset else "")
    return [
        Step("Link and drive", REMARK if c.fault_reset else PASS, describe_info(c.info) + fault),
        Step("Limits", PASS, f"{_limits_text(r)} ({r.limits.how}); enforced by the Drive layer"),
        _bump_step(r),
        _sidbe_step(r),
        _diagnose_step(r),
        *_design_steps(r),
    ]


def verdict(done: list[Step]) -> Verdict:
    """The page's verdict from the steps."""
    failed = [s.name for s in done if s.status == FAIL]
    remarks = [s.name for s in done if s.status == REMARK]
    if failed:
        return Verdict(FAIL, f"FAIL: {', '.join(failed)} did not pass; do not program these values "
                       "before the cause is found")  # fmt: skip
    if remarks:
        return Verdict(REMARK, f"PASS with remarks ({', '.join(remarks)}): the axis is identified and "
                       "the values below may be programmed; read the remarks")  # fmt: skip
    return Verdict(PASS, "PASS: the axis is identified and the values below may be programmed into the drive")


def identity(r: RecordInputs) -> KeyValues:
    """Who, where and which drive."""
    given, info = r.config.identity, r.check.info
    missing = "not given in the config [identity]"
    told = f"not reported by the {info.transport} protocol"
    return KeyValues("Identity", [
        ("site", given.site or missing), ("machine", given.machine or missing),
        ("axis", given.axis or missing), ("operator", given.operator or missing),
        ("date", r.started),
        ("drive vendor", info.vendor or told), ("drive product", info.product or told),
        ("firmware", info.firmware or told), ("serial number", info.serial_number or told),
        ("drive URL (with the confirmed limits)", r.url),
    ])  # fmt: skip


def summary_section(r: RecordInputs, done: list[Step]) -> Section:
    res = r.sidbe.result
    blocks: list = [
        Grid("Steps", ("step", "result", "detail"), [(s.name, s.status.upper(), s.detail) for s in done],
             classes=[("", s.status, "") for s in done]),
        Grid("Identified model (± 1 sigma)", ("quantity", "value ± 1 sigma", "unit"), model_rows(res)),
        f"Verification by simulation: fit {res.fit_percent:.2f} %. {res.selection}",
    ]  # fmt: skip
    if not r.units.known:
        blocks.append(NO_UNITS + ".")
    return Section("Summary", blocks)


def program_section(r: RecordInputs) -> Section:
    rows = [
        (p.name, "", "", "", "", p.note) if math.isnan(p.value)
        else (p.name, p.value, p.unit, p.drive_value, p.drive_unit, p.note)
        for p in r.program
    ]  # fmt: skip
    logged = "SI value" if r.units.si else "value as logged"
    header = ("quantity", logged, "unit", "in the drive's own units", "drive unit", "note")
    if r.scale.reported:
        intro = ("The drive's own units, as its driver reports them: "
                 + "; ".join(r.scale.definitions(r.units)) + ".")  # fmt: skip
    else:
        intro = ("The drive reports no scale factors: it takes the values in the units of its log "
                 f"(u in {r.units.of('u')}, v in {r.units.of('v')}), so both columns agree.")  # fmt: skip
    src = r.source
    if src is not None and src.origin == DIAGNOSE:
        res = r.sidbe.result.model
        intro = (f"These values come from the diagnosed model: {src.description}. The SIDBE base fit, "
                 f"biased by what it lacks (Coulomb +{res.coulomb_pos:.4g} / -{res.coulomb_neg:.4g} against "
                 f"+{src.model.coulomb_pos:.4g} / -{src.model.coulomb_neg:.4g} {r.units.of('u')} refitted), "
                 "stays in the summary as evidence. " + intro)  # fmt: skip
    blocks: list = [intro, Grid("", header, rows, css="program")]
    return Section("Values to program into the drive", blocks)


def _drive_section(r: RecordInputs) -> Section:
    c, info = r.check, r.check.info
    rows = [
        ("identity", describe_info(info)),
        ("fault on connecting", f"0x{c.fault_found:04X}" if c.fault_found else "none"),
        ("fault reset", "yes" if c.fault_reset else "no"),
        ("signal units (log)", f"u: {r.units.of('u')}, v: {r.units.of('v')}, x: {r.units.of('x')}"),
    ]
    unit = {"max_u": r.units.of("u"), "max_v": r.units.of("v"), "xmin": r.units.of("x"), "xmax": r.units.of("x")}
    lim = [*((f"{k} [{unit[k]}]", v) for k, v in r.limits.as_dict().items()), ("confirmed", r.limits.how)]
    return Section("Drive and limits", [KeyValues("Drive", rows),
                                        KeyValues("Limits (enforced by the Drive layer)", lim)], level=3)  # fmt: skip


def _bump_section(r: RecordInputs) -> Section:
    runs = [run for run in read_log(r.bump.log_path).runs if run.v is not None]
    t = np.concatenate([run.t for run in runs])
    png = figures.bump(t, np.concatenate([run.u for run in runs]), np.concatenate([run.v for run in runs]), r.units)
    u, v = r.units.of("u"), r.units.of("v")
    rows = [
        (f"moves at + (pulse magnitude) [{u}]", r.bump.breakaway_pos),
        (f"moves at - (pulse magnitude) [{u}]", r.bump.breakaway_neg),
        ("direction", "positive command gives positive velocity"),
        ("position vs integrated velocity", "consistent" if r.bump.position_checked else "too small to judge"),
        (f"motion threshold [{v}]", r.bump.speed_threshold),
    ]
    caption = ("Bump test: short command pulses each way, smallest first, until the axis moves; "
               "the velocity shows that it moved and in which direction.")  # fmt: skip
    return Section("Bump test", [KeyValues("", rows), Figure(caption, png)], level=3)


def _excitation_section(r: RecordInputs) -> Section:
    d = r.sidbe.details
    u = r.units.of("u")
    start, stop, index, periods = figures.period_window(r.log)
    freqs = d.get("freqs", [])
    rows = [
        (f"amplitude u1 [{u}]", d.get("amplitude", math.nan)), ("ratio u2/u1", d.get("ratio", math.nan)),
        ("sample rate [Hz]", d.get("fs", math.nan)), ("periods per run", d.get("periods", periods)),
        ("excited lines [Hz]", ", ".join(f"{f:g}" for f in freqs) if freqs else "not recorded"),
        ("rounds", "; ".join(f"#{it['index']} ±{it['amplitude']:g}: "
                             + ("no model" if it.get("fit_percent") is None else f"{it['fit_percent']:.2f} %")
                             for it in d.get("iterations", []))),
    ]  # fmt: skip
    hold = d.get("hold")
    caption = (f"One excitation period (period {index} of {periods}, steady state) of both runs: the "
               "binary multisine u1 and u2 = ratio x u1 (top) and the velocity each produced (bottom).")  # fmt: skip
    window = None
    if isinstance(hold, dict):
        rows += _hold_rows(hold, r.units)
        window = (r.limits.xmin, r.limits.xmax)
        caption = (f"One excitation period (period {index} of {periods}, steady state) of both runs, "
                   "excited in closed loop: the binary multisine u1 and u2 = ratio x u1 with the total "
                   "command the hold loop made of it (top), the velocity (middle), and the position "
                   "against the held one and the travel limits (bottom).")  # fmt: skip
    return Section("Excitation", [KeyValues("SIDBE excitation", rows),
                                  Figure(caption, figures.excitation_period(r.log, r.units, window))],
                   level=3)  # fmt: skip


def _hold_rows(hold: dict, units: SignalUnits) -> list[tuple[str, object]]:
    """The closed loop's facts: where the hold ran, its gains, the travel it used."""
    u, x, v = units.of("u"), units.of("x"), units.of("v")
    where = ("the drive's own position loop (gains fitted to a trial)" if hold.get("where") == "drive"
             else "host-side position loop")  # fmt: skip
    learnt = "the bump test" if "known" in hold else "a relay probe (probe.csv)" if "probe" in hold else "-"
    bandwidth = hold.get("bandwidth_hz")
    return [
        ("loop", f"closed: {where}, designed from {learnt}"),
        (f"held position x_ref [{x}]", hold.get("x_ref", math.nan)),
        (f"hold gains kp [{u}/{x}], ki [{u}/({x} s)], kd [{u}/({v})]",
         ", ".join(f"{hold.get(k, math.nan):.4g}" for k in ("kp", "ki", "kd"))),
        ("hold bandwidth [Hz]", "-" if bandwidth is None else f"{bandwidth:.3g}"),
        ("travel used", f"{hold.get('travel_share', math.nan):.0%} of the room of {hold.get('room', math.nan):.4g} "
                        f"{x} around x_ref"),
    ]  # fmt: skip


#: Identification plots (servobench.bench.report.plots, written by the SIDBE procedure) -> section title.
SIDBE_PLOTS = {
    plots.TIME_FILE: "Velocities",
    plots.FRF_FILE: "Frequency response",
    plots.FRICTION_FILE: "Friction-velocity map",
}


def _plot_sections(r: RecordInputs) -> list[Section]:
    written = {p.name: p for p in r.sidbe.plots}
    captions = plots.captions(r.sidbe.result)
    out = []
    for name, title in SIDBE_PLOTS.items():
        if name in written:
            out.append(Section(title, list(png_files([written[name]], captions)), level=3))
        else:
            why = "the log holds no u1/u2 pair" if name == plots.FRF_FILE else "the procedure wrote none"
            out.append(Section(title, [f"Not available: {why}."], level=3))
    return out


def _diagnose_section(r: RecordInputs) -> Section:
    d = r.diag
    rows = [
        ("effects added", ", ".join(d.effects) or "none"),
        ("velocity gap before [% NRMSE]", d.gap_before),
        ("velocity gap after [% NRMSE]", d.gap_after),
    ]
    blocks: list = [d.note] if d.note else []
    blocks += [KeyValues("", rows), *png_files(d.plots, DIAGNOSE_CAPTIONS)]
    return Section("Diagnosis (before / after)", blocks, level=3)


def _design_section(r: RecordInputs) -> Section:
    pi, chk, v = r.design.pi, r.design.check, r.units.of("v")
    rows = [
        ("crossover [Hz]", pi.crossover_hz), ("phase margin [deg]", pi.phase_margin_deg),
        ("gain margin [dB]", pi.gain_margin_db), ("crossover limited by", pi.limited_by),
        ("delay [cycles]", pi.delay_cycles),
        (f"reference amplitude [{v}]", chk.amplitude), ("reference frequency [Hz]", chk.frequency_hz),
        (f"rms tracking error, PI alone [{v}]", chk.without_ff.rms_error),
        (f"rms tracking error, PI + feed-forward [{v}]", chk.with_ff.rms_error),
        (f"largest tracking error, PI alone [{v}]", chk.without_ff.max_error),
        (f"largest tracking error, PI + feed-forward [{v}]", chk.with_ff.max_error),
    ]  # fmt: skip
    text = ("Feed-forward u_ff = viscous x r + Coulomb(sign r), from the reference velocity r; PI on the "
            "velocity error. Checked by simulating the loop on the identified plant with its Coulomb "
            "friction, at the design's sample time and delay, with the command clamped to max_u.")  # fmt: skip
    caption = ("A slow reversing reference on the identified plant (simulation): PI alone sticks at each "
               "reversal until the integrator builds up the breakaway command; the feed-forward supplies it.")  # fmt: skip
    return Section("Friction compensation and velocity-loop PI", [
        text, KeyValues("Margins and simulation check", rows), Figure(caption, figures.compensation(chk, r.units)),
    ], level=3)  # fmt: skip


def page(r: RecordInputs) -> str:
    """The whole ``report.html`` text."""
    done = steps(r)
    given = r.config.identity
    where = " ".join(p for p in (given.machine, f"axis {given.axis}" if given.axis else "") if p)
    title = f"Commissioning record: {where}" if where else "Commissioning record"
    evidence = [
        _drive_section(r), _bump_section(r), _excitation_section(r), *_plot_sections(r),
        _diagnose_section(r), _design_section(r),
    ]  # fmt: skip
    sections = [summary_section(r, done), program_section(r),
                Section("Evidence", ["What the verdict and the values rest on, step by step."]), *evidence]  # fmt: skip
    footer = f"servobench {r.version}; record started {r.started}; log {r.sidbe.log_path.name}"
    return render(title, verdict(done), identity(r), sections, footer)
