"""``servobench diagnose LOG [--json] [--out DIR]``: name the effect the model lacks, and say
whether the model then explains the data.

Identifies the base model (linear block + Coulomb per direction), compares
it with the measured velocity, looks for the signatures of the library's
effects (:mod:`servobench.sim_backend.physics.effects`), adds what pays on held-out data,
and judges the final model against the noise floor (``explained`` or
``unexplained``, and where the residual lives). The text output leads with
that verdict; ``--json`` prints exactly one JSON object; ``--out DIR`` writes
``report.md``, ``model.json`` (loadable by ``servobench validate``),
``comparison.csv`` and the figures. The exit status is 0 whatever the
verdict. Progress goes to stderr, stage by stage.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("log", metavar="LOG", help="servobench CSV log or MATLAB .mat file")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    p.add_argument(
        "--out",
        metavar="DIR",
        help="write report.md, model.json, comparison.csv and the figures here",
    )
    p.add_argument(
        "--mat-map",
        metavar="MAP",
        help="variable mapping for .mat logs, e.g. t=t,u=vir*gtau,x=qm",
    )
    p.add_argument(
        "--horizon",
        type=float,
        metavar="SECONDS",
        help="compare by predictions restarted from the measured state every SECONDS "
        "(default: whole-run simulation; 0.5 s for logs marked 'loop = closed')",
    )


@contextmanager
def stage_progress() -> Iterator[Callable[[str], None]]:
    """Yield ``say(message)``: a spinner with the stage and the elapsed time on a terminal's
    stderr, one line per stage otherwise."""
    from rich.console import Console

    console = Console(stderr=True)
    t0 = time.monotonic()
    if not console.is_terminal:

        def line(message: str) -> None:
            print(f"diagnose [{time.monotonic() - t0:5.1f} s]: {message}", file=sys.stderr)

        yield line
        return
    with console.status("diagnose: reading the log") as status:

        def spin(message: str) -> None:
            status.update(f"diagnose [{time.monotonic() - t0:4.0f} s]: {message}")

        yield spin


def run(args: argparse.Namespace) -> int:
    import json

    from servobench.bench.diagnose.workflow import diagnose
    from servobench.bench.logio import read_log
    from servobench.bench.report.diagnose import summary_lines, to_json, write_report

    log = read_log(args.log, args.mat_map)
    with stage_progress() as say:
        result = diagnose(log, horizon_s=args.horizon, progress=say)
        if args.out:
            say("writing the report")
        report = write_report(result, args.out) if args.out else None
    if args.json:
        print(json.dumps(to_json(result)))
        return 0
    for line in summary_lines(result):
        print(line)
    if report is not None:
        print(f"report: {report}")
        print(f"model: {report.parent / 'model.json'}")
    return 0
