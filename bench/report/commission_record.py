"""Assemble the report sections from the commissioning results (figures included)."""

from __future__ import annotations

import math
from collections.abc import Mapping

from servobench.bench.commission.bump import BumpResult
from servobench.bench.commission.checks import DriveCheck, describe_info
from servobench.bench.commission.integration import DiagnoseOutcome, SidbeOutcome
from servobench.bench.commission.limits import ConfirmedLimits
from servobench.bench.commission.record import Design, derived_std
from servobench.bench.logio import ExperimentLog, read_log
from servobench.bench.report import commission_figures as figures
from servobench.bench.report.html import Section, png_files


def _pm(value: float, std: float) -> str:
    return f"{value:.6g} ± {std:.2g}" if math.isfinite(std) else f"{value:.6g}"


def drive_section(check: DriveCheck, limits: ConfirmedLimits, url: str) -> Section:
    info = check.info
    rows = [
        ("drive URL (with limits)", url),
        ("identity", describe_info(info)),
        ("fault on connecting", f"0x{check.fault_found:04X}" if check.fault_found else "none"),
        ("fault reset", "yes" if check.fault_reset else "no"),
        ("units", ", ".join(f"{k}: {v}" for k, v in info.units.items()) or "not reported"),
    ]
    lim = [(k, v) for k, v in limits.as_dict().items()] + [("confirmed", limits.how)]
    return Section("Drive and limits", tables=[("Drive", rows), ("Limits (enforced by the Drive layer)", lim)])


def bump_section(bump: BumpResult) -> Section:
    log = read_log(bump.log_path)
    runs = [r for r in log.runs if r.v is not None]
    import numpy as np

    t = np.concatenate([r.t for r in runs])
    png = figures.bump(t, np.concatenate([r.u for r in runs]), np.concatenate([r.v for r in runs]))
    rows = [
        ("moves at + (pulse magnitude)", bump.breakaway_pos),
        ("moves at - (pulse magnitude)", bump.breakaway_neg),
        ("direction", "positive command gives positive velocity"),
        ("position vs integrated velocity", "consistent" if bump.position_checked else "too small to judge"),
        ("motion threshold [velocity units/s]", bump.speed_threshold),
    ]
    return Section("Bump test", tables=[("", rows)], figures=[("Bump test: command and velocity", png)])


def model_section(sidbe: SidbeOutcome) -> Section:
    result = sidbe.result
    model, std = result.model, result.std
    derived = derived_std(result)
    rows = [
        ("M (inertia)", _pm(model.M, std.get("M", math.nan))),
        ("B (viscous)", _pm(model.B, std.get("B", math.nan))),
        ("pole -B/M [1/s]", _pm(model.pole, derived["pole"])),
        ("DC gain 1/B", _pm(model.dc_gain, derived["dc_gain"])),
        ("Coulomb + [command units]", _pm(model.coulomb_pos, std.get("coulomb_pos", math.nan))),
        ("Coulomb - [command units]", _pm(model.coulomb_neg, std.get("coulomb_neg", math.nan))),
        ("fit [%]", result.fit_percent),
        ("method", result.method),
        ("selection", result.selection),
    ]
    details = [(k, v) for k, v in sidbe.details.items() if isinstance(v, (int, float, str))]
    tables = [("Identified model (± 1 sigma)", rows)]
    if details:
        tables.append(("SIDBE procedure", details))
    return Section("Identified model", tables=tables)


#: Plots of the SIDBE procedure (servobench.bench.report.plots) -> report section.
SIDBE_PLOTS = {
    "time.png": "Velocities",
    "frf.png": "Frequency response",
    "friction.png": "Friction-velocity map",
}


def plot_sections(log: ExperimentLog, sidbe: SidbeOutcome) -> list[Section]:
    """Excitation, then the procedure's velocity, FRF and friction plots."""
    out = [Section("Excitation", figures=[("Excitation command per run", figures.excitation(log))])]
    written = {p.name: p for p in sidbe.plots}
    for name, title in SIDBE_PLOTS.items():
        if name in written:
            out.append(Section(title, figures=png_files([written[name]])))
        else:
            out.append(Section(title, paragraphs=[f"not available: the procedure wrote no {name}"]))
    rest = [p for p in sidbe.plots if p.name not in SIDBE_PLOTS]
    if rest:
        out.append(Section("More identification plots", figures=png_files(rest)))
    return out


def diagnose_section(diag: DiagnoseOutcome) -> Section:
    rows = [
        ("effects added", ", ".join(diag.effects) or "none"),
        ("velocity gap before [% NRMSE]", diag.gap_before),
        ("velocity gap after [% NRMSE]", diag.gap_after),
    ]
    return Section(
        "Diagnosis (before / after)",
        paragraphs=[diag.note] if diag.note else [],
        tables=[("", rows)],
        figures=png_files(diag.plots),
    )


def design_section(design: Design, units: Mapping[str, str]) -> Section:
    ff, pi, chk = design.feed_forward, design.pi, design.check
    ff_rows = [
        ("Coulomb, positive motion [command units]", ff.coulomb_pos),
        ("Coulomb, negative motion [command units]", ff.coulomb_neg),
        ("viscous [command units per velocity unit/s]", ff.viscous),
        ("sign band [velocity units/s]", ff.sign_band),
    ]
    pi_rows = [
        ("Kp [command units per velocity unit/s]", pi.kp),
        ("Ki [command units per velocity unit]", pi.ki),
        ("Ti [s]", pi.ti_s),
        ("sample time [s]", pi.sample_time_s),
        ("delay [cycles]", pi.delay_cycles),
        ("crossover [Hz]", pi.crossover_hz),
        ("phase margin [deg]", pi.phase_margin_deg),
        ("gain margin [dB]", pi.gain_margin_db),
        ("crossover limited by", pi.limited_by),
    ]
    chk_rows = [(k.replace("_", " "), v) for k, v in chk.as_dict().items()]
    text = (
        "Feed-forward u_ff = viscous * r + Coulomb(sign r), from the reference velocity r; "
        "PI on the velocity error. Checked by simulating the loop on the identified plant with "
        f"Coulomb friction: the RMS tracking error changes by a factor {chk.rms_ratio:.3g} with compensation."
    )
    return Section(
        "Friction compensation and velocity-loop PI",
        paragraphs=[text],
        tables=[("Friction feed-forward", ff_rows), ("Velocity PI", pi_rows), ("Simulation check", chk_rows)],
        figures=[("Tracking a slow reversing reference", figures.compensation(chk))],
    )
