"""``servobench identify LOG``: identify the model from a log (CSV or MATLAB .mat)."""

from __future__ import annotations

import argparse

from servobench.bench.commands.log_args import add_log_arguments, read_log_of


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_log_arguments(p)
    p.add_argument(
        "--method",
        choices=("auto", "sidbe", "joint"),
        default="auto",
        help="sidbe (needs the u1/u2 pair), joint (any log), or auto (default: both when possible, "
        "the better on held-out data)",
    )
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    p.add_argument("--resonance", action="store_true", help="let SIDBE fit a series resonance")
    p.add_argument(
        "--cutoff",
        type=float,
        default=None,
        metavar="HZ",
        help="cut-off of the zero-phase position filter for logs without velocity (default fs/20)",
    )
    p.add_argument(
        "--loop",
        choices=("open", "closed"),
        default=None,
        help="how the log was recorded, overriding its 'loop' metadata: open-loop position-only logs "
        "get a simulation-error refinement, closed-loop ones inverse-dynamic least squares only",
    )
    p.add_argument("--plots", default=None, metavar="DIR", help="also write PNG plots to DIR")


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace
    from pathlib import Path

    from servobench.bench.identify.auto import identify
    from servobench.bench.report.summary import print_json, print_result

    log = read_log_of(args)
    if args.loop:
        log = replace(log, metadata={**log.metadata, "loop": args.loop})
    result = identify(log, args.method, resonance=args.resonance, velocity_cutoff_hz=args.cutoff)
    if args.plots:
        from servobench.bench.report.plots import write_plots

        out = Path(args.plots)
        out.mkdir(parents=True, exist_ok=True)
        write_plots(result, out)
    if args.json:
        print_json(result.to_json())
    else:
        print_result(result, f"Identified model: {args.log}")
    return 0
