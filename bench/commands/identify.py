"""``servobench identify LOG``: identify the model from a log (CSV or MATLAB .mat).

``--out DIR`` writes ``model.json`` (the ``--json`` object: the model keys, ``fs``,
``drive_scale`` when the log states the drive's scale factors, and ``log``)
and the PNG plots, as ``sidbe`` does; a folder that holds a ``model.json``
already is refused before anything is identified. ``servobench validate``
and ``servobench program`` read that model.json.
"""

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
    p.add_argument("--out", default=None, metavar="DIR",
                   help="write model.json and the PNG plots to DIR (refused when DIR holds a model.json)")  # fmt: skip


def run(args: argparse.Namespace) -> None:
    import json
    from dataclasses import replace
    from pathlib import Path

    from servobench.bench.identify.auto import identify
    from servobench.bench.model.program import drive_scale_json
    from servobench.bench.procedure.run_folder import MODEL_FILE
    from servobench.bench.report.summary import print_json, print_result
    from servobench.errors import UsageError

    out_dir = Path(args.out) if args.out else None
    if out_dir is not None and (out_dir / MODEL_FILE).exists():
        raise UsageError(f"{out_dir} already holds a {MODEL_FILE}; choose another --out, or move it away "
                         "first: nothing was overwritten")  # fmt: skip
    log = read_log_of(args)
    if args.loop:
        log = replace(log, metadata={**log.metadata, "loop": args.loop})
    result = identify(log, args.method, resonance=args.resonance, velocity_cutoff_hz=args.cutoff)
    from servobench.bench.report.plots import write_plots

    for folder in {Path(d) for d in (args.plots, args.out) if d}:
        folder.mkdir(parents=True, exist_ok=True)
        write_plots(result, folder)
    doc = {**result.to_json(), "fs": log.fs_hz, "log": args.log,
           **({"drive_scale": scale} if (scale := drive_scale_json(log.metadata, args.log)) else {})}  # fmt: skip
    if out_dir is not None:
        (out_dir / MODEL_FILE).write_text(json.dumps(doc, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    if args.json:
        print_json(doc)
    else:
        print_result(result, f"Identified model: {args.log}")
        if out_dir is not None:
            print(f"output: {out_dir}")
    return None
