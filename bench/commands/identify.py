"""``servobench identify LOG``: identify the model from a log (CSV or MATLAB .mat).

``--out DIR`` writes ``model.json`` (the ``--json`` object: the model keys, ``fs``,
``drive_scale`` when the log states the drive's scale factors, and ``log``)
and the PNG plots, as ``sidbe`` does; a folder that holds a ``model.json``
already is refused before anything is identified. ``servobench validate``
and ``servobench program`` read that model.json.
"""

from __future__ import annotations

import argparse

from servobench.bench.commands.log_args import add_log_arguments


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
    p.add_argument("--out", default=None, metavar="DIR",
                   help="write model.json and the PNG plots to DIR (refused when DIR holds a model.json)")  # fmt: skip


def run(args: argparse.Namespace) -> None:
    from pathlib import Path

    from servobench.analysis import identify
    from servobench.bench.report.summary import print_json, print_result

    model = identify(args.log, method=args.method, resonance=args.resonance, cutoff_hz=args.cutoff,
                     loop=args.loop, out=args.out or None, plots=args.plots or None,
                     columns=args.columns, mat_map=args.mat_map)  # fmt: skip
    if args.json:
        print_json(model.to_dict())
    else:
        print_result(model.details, f"Identified model: {args.log}")
        if args.out:
            print(f"output: {Path(args.out)}")
    return None
