"""``servobench validate MODEL LOG``: how well a saved model reproduces another log.

MODEL is any model servobench writes (``identify --json``, ``diagnose --json``,
the ``model.json`` of ``sidbe`` and ``commission``); LOG any log ``identify``
reads. Prints ``fit_percent`` and ``gap_percent`` with the definitions of
``identify`` and ``diagnose``, and for closed-loop logs the relative force
error of the EMPS reference (see :mod:`servobench.bench.model.validate`).

The verdict leads: the first line is ``PASS: ...`` when ``fit_percent`` is at
least ``--min-fit`` (default 90 %, the SIDBE verification threshold) and
``gap_percent`` at most ``--max-gap`` (default 10 %), else ``FAIL: ...`` and
exit status 3; under ``--json`` the object's first key is ``verdict``.
"""

from __future__ import annotations

import argparse

from servobench.bench.commands.log_args import add_log_arguments
from servobench.bench.model.validate import DEFAULT_MAX_GAP_PERCENT, DEFAULT_MIN_FIT_PERCENT


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", metavar="MODEL", help="model file: identify --json / diagnose --json output, or model.json")
    add_log_arguments(p)
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    p.add_argument(
        "--loop",
        choices=("open", "closed"),
        default=None,
        help="how LOG was recorded, overriding its 'loop' metadata (closed adds force_error_percent)",
    )
    p.add_argument("--out", metavar="DIR", default=None, help="write the measured-against-predicted plot here")
    p.add_argument("--min-fit", type=float, default=DEFAULT_MIN_FIT_PERCENT, metavar="PCT",
                   help=f"least fit_percent that passes (default {DEFAULT_MIN_FIT_PERCENT:g})")
    p.add_argument("--max-gap", type=float, default=DEFAULT_MAX_GAP_PERCENT, metavar="PCT",
                   help=f"largest gap_percent that passes (default {DEFAULT_MAX_GAP_PERCENT:g})")  # fmt: skip


def run(args: argparse.Namespace):
    from servobench.analysis import validate
    from servobench.bench.report.summary import print_json
    from servobench.model import saved_model

    check = validate(args.model, args.log, loop=args.loop, min_fit_percent=args.min_fit,
                     max_gap_percent=args.max_gap, out=args.out or None, columns=args.columns,
                     mat_map=args.mat_map)  # fmt: skip
    if args.json:
        print_json(check.to_dict())
        return check.verdict
    result, effects = check.details, list(check.model.effects)
    print(check.headline)
    print(f"model {args.model} ({saved_model(check.model).kind}{', effects: ' + ', '.join(effects) if effects else ''})")
    print(f"log   {args.log}: {result.samples:,} samples, {len(result.runs)} run(s), {result.comparison}")
    print(f"fit_percent         {result.fit_percent:8.3f} %")
    print(f"gap_percent         {result.gap_percent:8.3f} %")
    if result.force_error_percent is not None:
        print(f"force_error_percent {result.force_error_percent:8.3f} %")
    for note in result.notes:
        print(f"note: {note}")
    if check.figure is not None:
        print(f"figure: {check.figure}")
    return check.verdict
