"""``servobench run --drive URL --out LOG``: apply u1 and u2 to a drive and log them, nothing else.

On an axis with limited travel (``--loop auto``, the default, with
``xmin``/``xmax`` in the URL, or ``--loop closed``) the runs are streamed in
closed loop under a hold loop that keeps the axis inside its window; a relay
probe first learns the axis (``LOG-probe.csv`` beside the log).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from servobench.bench.commands.excitation_args import (
    add_excitation_arguments,
    check_amplitude,
    design_from_args,
    link_rate_hz,
    parse_freqs,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_excitation_arguments(p)
    p.add_argument(
        "--out", required=True, metavar="LOG", help="CSV log to write (run 1 = u1, run 2 = u2)"
    )
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def run(args: argparse.Namespace) -> int:
    from servobench.bench.commands.progress import stream_progress
    from servobench.bench.commands.sidbe import note
    from servobench.bench.procedure.excitation import design_excitation
    from servobench.bench.procedure.sidbe import SidbeOptions, rate_note
    from servobench.bench.report.summary import print_json
    from servobench.bench.run.runner import stream_runs
    from servobench.drivers.registry import open_drive

    drive = open_drive(args.drive)
    fs_hz = link_rate_hz(args.fs, drive)  # refused before the port is opened
    if text := rate_note(args.fs, drive):
        note(text)
    design = design_from_args(args, fs_hz)
    options = SidbeOptions(
        amplitude=args.amplitude, ratio=args.ratio, fs_hz=fs_hz, periods=args.periods,
        period_s=args.period, freqs_hz=parse_freqs(args.freqs), loop=args.loop,
    )  # fmt: skip
    if args.amplitude is not None or not options.closed(drive):
        check_amplitude(design.amplitude, drive.limits.max_command)
    out = Path(args.out)
    if out.parent and not out.parent.exists():
        out.parent.mkdir(parents=True)
    hold = None
    with drive, stream_progress() as progress:
        tick = lambda done, total: progress(1, done, total)  # noqa: E731
        if options.closed(drive):
            res, design, hold = _closed(drive, options, out, tick)
        else:
            meta = {**design.metadata(), "loop": "open"}
            excitation = design_excitation(design)
            res = stream_runs(drive, excitation.runs(), design.fs_hz, out, metadata=meta, progress=tick)
    if args.json:
        extra = {"loop": "open"} if hold is None else {"loop": "closed", "hold": hold}
        print_json({"log": str(res.log_path), "samples": res.samples, "complete": True,
                    "fs_achieved": res.fs_achieved_hz, **design.metadata(), **extra,
                    **cycle_json(res)})  # fmt: skip
    else:
        where = "" if hold is None else (
            f", closed loop ({hold['where']}-side hold, {hold['travel_share']:.0%} of the room used)"
        )
        print(
            f"wrote {res.log_path} ({res.samples} samples, runs 1 and 2, amplitude ±{design.amplitude:g}, "
            f"{design.fs_hz:g} Hz, achieved {res.fs_achieved_hz:.6g} Hz{where})"
        )
        c = res.cycle_timing
        if c is not None:
            print(
                f"timing: clock_source {res.clock_source}, host jitter p50/p99/max "
                f"{c.jitter_p50_s * 1e3:.3g}/{c.jitter_p99_s * 1e3:.3g}/{c.jitter_max_s * 1e3:.3g} ms, "
                f"{c.missed_cycles} missed cycles, instants uncertain by {c.t_unc_p99_s * 1e3:.3g} ms (p99)"
            )
    return 0


def cycle_json(res) -> dict[str, object]:
    """``clock_source`` and ``timing`` (the host's cycle) of a real-time run; None in fast pace."""
    import math

    c = res.cycle_timing
    if c is None:
        return {"clock_source": None, "timing": None}
    fin = lambda x: x if math.isfinite(x) else None  # noqa: E731
    return {
        "clock_source": res.clock_source,
        "timing": {
            "clock_source": res.clock_source, "jitter_p50_s": fin(c.jitter_p50_s),
            "jitter_p99_s": fin(c.jitter_p99_s), "jitter_max_s": fin(c.jitter_max_s),
            "missed_cycles": c.missed_cycles, "late_cycles": c.late_cycles,
            "t_unc_p50_s": fin(c.t_unc_p50_s), "t_unc_p99_s": fin(c.t_unc_p99_s),
            "t_unc_max_s": fin(c.t_unc_max_s),
        },
    }  # fmt: skip


def _closed(drive, options, out: Path, tick):
    """Probe, plan and stream in closed loop; the result, the design applied and the hold's facts."""
    from servobench.bench.procedure.closed_rounds import facts, prepare
    from servobench.bench.procedure.excitation import design_excitation
    from servobench.bench.run.closed import stream_closed_runs
    from servobench.bench.run.runner import default_pace

    pace = drive.url.get_str("pace", "") or default_pace(drive)
    probe_log = out.with_name(out.stem + "-probe.csv")
    trial_log = out.with_name(out.stem + "-hold-trial.csv")
    plan, learnt, _ = prepare(drive, options, probe_log, trial_log, pace)
    design = plan.design
    res = stream_closed_runs(drive, design_excitation(design).runs(), design.fs_hz, out, plan,
                             metadata=design.metadata(), pace=pace, progress=tick)  # fmt: skip
    return res, design, {**facts(plan), "travel_share": res.share, **learnt}
