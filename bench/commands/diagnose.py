"""``servobench diagnose LOG [--json] [--out DIR]``: name the effect the model lacks.

Identifies the base model (linear block + Coulomb per direction), compares
it with the measured velocity, looks for the signatures of the library's
effects (:mod:`servobench.sim_backend.physics.effects`), adds what pays on held-out data and
reports the velocity gap before and after. ``--json`` prints exactly one JSON
object; ``--out DIR`` writes ``comparison.csv``, plots and ``report.md``.
"""

from __future__ import annotations

import argparse

from servobench.bench.commands.log_args import add_log_arguments, read_log_of


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_log_arguments(p)
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    p.add_argument("--out", metavar="DIR", help="write comparison.csv, plots and report.md here")
    p.add_argument(
        "--horizon",
        type=float,
        metavar="SECONDS",
        help="compare by predictions restarted from the measured state every SECONDS "
        "(default: whole-run simulation; 0.5 s for logs marked 'loop = closed')",
    )


def run(args: argparse.Namespace) -> int:
    import json

    from servobench.bench.diagnose.workflow import diagnose
    from servobench.bench.report.diagnose import to_json, write_report

    log = read_log_of(args)
    result = diagnose(log, horizon_s=args.horizon)
    report = write_report(result, args.out) if args.out else None
    if args.json:
        print(json.dumps(to_json(result)))
        return 0
    print(f"comparison: {result.data.comparison}")
    print(f"velocity gap: {result.gap_before:.3g}% before, {result.gap_after:.3g}% after")
    if not result.effects:
        print("no effect named: nothing in the library pays on held-out data")
    for i, e in enumerate(result.effects, 1):
        params = ", ".join(f"{k}={v:.4g}" for k, v in e.parameters.items())
        print(f"{i}. {e.name} ({params})")
        print(f"   {e.evidence}")
    if report is not None:
        print(f"report: {report}")
    return 0
