"""``servobench run --drive URL --out LOG``: apply u1 and u2 to a drive and log them, nothing else."""

from __future__ import annotations

import argparse
from pathlib import Path

from servobench.bench.commands.excitation_args import (
    add_excitation_arguments,
    check_amplitude,
    design_from_args,
    link_rate_hz,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_excitation_arguments(p)
    p.add_argument(
        "--out", required=True, metavar="LOG", help="CSV log to write (run 1 = u1, run 2 = u2)"
    )
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def run(args: argparse.Namespace) -> int:
    from servobench.bench.commands.progress import stream_progress
    from servobench.bench.excitation import design_excitation
    from servobench.bench.report.summary import print_json
    from servobench.bench.run.runner import stream_runs
    from servobench.drivers.registry import open_drive

    drive = open_drive(args.drive)
    design = design_from_args(args, link_rate_hz(args.fs, drive))
    check_amplitude(design.amplitude, drive.limits.max_command)
    out = Path(args.out)
    if out.parent and not out.parent.exists():
        out.parent.mkdir(parents=True)
    excitation = design_excitation(design)
    meta = {**design.metadata(), "loop": "open"}
    with drive, stream_progress() as progress:
        res = stream_runs(
            drive,
            excitation.runs(),
            design.fs_hz,
            out,
            metadata=meta,
            progress=lambda done, total: progress(1, done, total),
        )
    if args.json:
        print_json(
            {
                "log": str(res.log_path),
                "samples": res.samples,
                "complete": res.complete,
                "fs_achieved": res.fs_achieved_hz,
                **design.metadata(),
            }
        )
    else:
        print(
            f"wrote {res.log_path} ({res.samples} samples, runs 1 and 2, amplitude ±{design.amplitude:g}, "
            f"{design.fs_hz:g} Hz, achieved {res.fs_achieved_hz:.6g} Hz)"
        )
    return 0
