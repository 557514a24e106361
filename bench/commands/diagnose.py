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
verdict. On a terminal, stderr shows the stage and the elapsed time while it runs.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from servobench.bench.commands.log_args import add_log_arguments


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_log_arguments(p)
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    p.add_argument(
        "--out",
        metavar="DIR",
        help="write report.md, model.json, comparison.csv and the figures here",
    )
    p.add_argument(
        "--horizon",
        type=float,
        metavar="SECONDS",
        help="compare by predictions restarted from the measured state every SECONDS "
        "(default: whole-run simulation; 0.5 s for logs marked 'loop = closed')",
    )


@contextmanager
def stage_progress(console=None) -> Iterator[Callable[[str], None]]:
    """Yield ``say(message)``: on a terminal's stderr, a spinner with the stage and the elapsed
    time, and at the end one line with the total time; nothing when stderr is not a terminal
    (an error then stays the one line on stderr)."""
    from rich.console import Console

    console = console or Console(stderr=True)
    if not console.is_terminal:
        yield lambda _m: None
        return
    t0 = time.monotonic()
    with console.status("diagnose: reading the log") as status:

        def spin(message: str) -> None:
            status.update(f"diagnose [{time.monotonic() - t0:4.0f} s]: {message}")

        yield spin
    console.print(f"diagnose: done in {time.monotonic() - t0:.0f} s", highlight=False)


def run(args: argparse.Namespace) -> int:
    import json

    from servobench.analysis import diagnose
    from servobench.bench.report.diagnose import summary_lines

    with stage_progress() as say:
        report = diagnose(args.log, horizon_s=args.horizon, out=args.out or None, progress=say,
                          columns=args.columns, mat_map=args.mat_map)  # fmt: skip
    if args.json:
        print(json.dumps(report.to_dict()))
        return 0
    for line in summary_lines(report.details):
        print(line)
    if report.report is not None:
        print(f"report: {report.report}")
        print(f"model: {report.report.parent / 'model.json'}")
    return 0
