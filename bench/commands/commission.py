"""``servobench commission --drive URL``: field commissioning with a record.

From "plugged in" to "identified, compensated, documented" in one command:
link and drive check, limits confirmed (terminal, or ``--config`` with
``--yes``), bump test, SIDBE with verification, diagnosis, friction
feed-forward and velocity-loop PI checked in simulation, and the record in
``--out`` (model.json, log.csv, bump.csv, report.html, commission.mat,
commission.json). The last line is the record's verdict, the banner of
``report.html``; ``commission.json`` leads with the same word (``verdict``).
Exit 0 when the verdict is a pass (with or without remarks), 3 when it ran
to the end and the verdict is a fail, 1 on a refusal or error, 130 on Ctrl-C
(the axis is left stopped and disabled; what was recorded is kept).
"""

from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--drive", required=True, metavar="URL", help="drive URL (see README: Drives)")
    p.add_argument("--config", metavar="TOML", help="commissioning config (see examples/bench.toml)")
    p.add_argument(
        "--yes", action="store_true",
        help="no questions: limits from --config (all required), one fault reset attempted",
    )  # fmt: skip
    p.add_argument(
        "--dry-run", action="store_true",
        help="read only: check and confirm, then say what would be done; nothing is written to the drive",
    )  # fmt: skip
    p.add_argument("--out", metavar="DIR", help="record folder (default: commission-<date>-<time>)")
    p.add_argument(
        "--record-bus", metavar="FILE",
        help="record raw bus traffic (candump .log, .blf, .asc, .csv) on transports that can",
    )  # fmt: skip


def run(args: argparse.Namespace):
    from servobench.procedures import commission

    result = commission(args.drive, config=args.config, out=args.out or None, yes=args.yes,
                        dry_run=args.dry_run, record_bus=args.record_bus or None)  # fmt: skip
    return result.verdict  # None after a dry run
