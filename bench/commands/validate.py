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

from servobench.bench.commands.log_args import add_log_arguments, read_log_of
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
    from servobench.bench.model.file import read_model
    from servobench.bench.model.validate import judge, validate
    from servobench.bench.report.summary import print_json
    from servobench.units import SignalUnits
    from servobench.verdict import Verdict

    saved = read_model(args.model)
    log = read_log_of(args)
    result = validate(saved.model, log, saved.effects, loop=args.loop)
    units = SignalUnits.from_metadata(log.metadata)
    mismatch = _unit_mismatch(saved.units, units)
    if mismatch:
        from dataclasses import replace

        result = replace(result, notes=(*result.notes, mismatch))
    figure = None
    if args.out:
        from servobench.bench.report.validation import write_validation_figure

        figure = write_validation_figure(result, args.out, units, title=log.source)
    judged = judge(result, args.min_fit, args.max_gap)
    verdict = Verdict.of(judged.passed)
    if args.json:
        out = {"verdict": verdict.word, **result.to_json(), "thresholds": judged.as_dict(), "model": args.model,
               "log": args.log, "effects": list(saved.effects), "units": units.as_metadata()}  # fmt: skip
        if figure is not None:
            out["figure"] = str(figure)
        print_json(out)
        return verdict
    print(verdict.line(f"{args.model} on {args.log}: {judged.text()}"))
    print(f"model {args.model} ({saved.kind}{', effects: ' + ', '.join(saved.effects) if saved.effects else ''})")
    print(f"log   {args.log}: {result.samples:,} samples, {len(result.runs)} run(s), {result.comparison}")
    print(f"fit_percent         {result.fit_percent:8.3f} %")
    print(f"gap_percent         {result.gap_percent:8.3f} %")
    if result.force_error_percent is not None:
        print(f"force_error_percent {result.force_error_percent:8.3f} %")
    for note in result.notes:
        print(f"note: {note}")
    if figure is not None:
        print(f"figure: {figure}")
    return verdict


def _unit_mismatch(model_units, log_units) -> str:
    """A note when the model's signal units (its ``units`` object) differ from the log's."""
    differ = [
        f"{k}: model [{model_units[k]}], log [{getattr(log_units, k)}]"
        for k in ("u", "v", "x")
        if model_units.get(k) and getattr(log_units, k) and model_units[k] != getattr(log_units, k)
    ]
    return ("units differ, the figures compare numbers in different units (" + "; ".join(differ) + ")"
            if differ else "")  # fmt: skip
