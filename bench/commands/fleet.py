"""``servobench fleet LOG_OR_DIR... --out DIR``: re-identify a fleet's logs on Dask and trend each axis.

Every log (named, or found under a named folder) is identified -- and with
``--diagnose`` diagnosed -- in parallel on Dask distributed: a local
cluster of ``--workers`` processes, or the workers of an existing scheduler
(``--scheduler tcp://host:8786``). Writes ``DIR/fleet.csv`` and
``DIR/fleet.parquet`` (one row per log) and ``DIR/trend.html``; flags an
axis whose Coulomb level or B drifted beyond ``--threshold`` percent, or
that shows an effect its first record did not. ``--json`` prints one
object. Exit 0, or 1 when some logs failed (their rows say why), 130 on
Ctrl-C (the cluster is shut down, the rows done so far are kept).
"""

from __future__ import annotations

import argparse
import sys

from servobench.bench.fleet.trend import DEFAULT_THRESHOLD_PERCENT


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "logs", nargs="+", metavar="LOG_OR_DIR", help="CSV logs, or folders searched for them"
    )
    p.add_argument(
        "--out",
        required=True,
        metavar="DIR",
        help="write fleet.csv, fleet.parquet, trend.html here",
    )
    where = p.add_mutually_exclusive_group()
    where.add_argument(
        "--workers", type=int, default=None, metavar="N",
        help="worker processes of the local Dask cluster (default: one per core)",
    )  # fmt: skip
    where.add_argument(
        "--scheduler", default=None, metavar="ADDRESS",
        help="run on an existing Dask scheduler instead, e.g. tcp://host:8786",
    )  # fmt: skip
    p.add_argument(
        "--diagnose", action="store_true", help="also diagnose every log (effects, gaps)"
    )
    p.add_argument(
        "--threshold", type=float, default=DEFAULT_THRESHOLD_PERCENT, metavar="PCT",
        help=f"drift of a Coulomb level or B that flags an axis [%%] (default {DEFAULT_THRESHOLD_PERCENT:g})",
    )  # fmt: skip
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def run(args: argparse.Namespace) -> int:
    from servobench.bench.commands.progress import count_progress
    from servobench.bench.fleet.engine import FleetInterrupted
    from servobench.errors import notes_of
    from servobench.procedures import fleet

    def started(text: str) -> None:
        print(f"servobench fleet: {text}", file=sys.stderr, flush=True)

    try:
        with count_progress(lambda total: f"identifying {total} logs") as progress:
            result = fleet(args.logs, args.out, workers=args.workers, scheduler=args.scheduler,
                           diagnose=args.diagnose, threshold_percent=args.threshold, progress=progress,
                           note=started)  # fmt: skip
    except FleetInterrupted as stop:  # during the jobs or the figures: the rows so far are kept
        return _interrupted("; ".join(["interrupted; Dask cluster shut down", *notes_of(stop)]), args)
    except KeyboardInterrupt as err:  # before the rows, or while writing the page (its note says so)
        return _interrupted("; ".join(notes_of(err)) or "interrupted; Dask cluster shut down, nothing written",
                            args)  # fmt: skip
    if args.json:
        from servobench.bench.report.summary import print_json

        print_json(result.to_dict())
    else:
        _print_text(result)
    return 1 if result.failed else 0


def _interrupted(message: str, args: argparse.Namespace) -> int:
    """Ctrl-C: one line on stderr (and ``{"error": ...}`` on stdout under ``--json``); 130."""
    print(f"servobench: {message}", file=sys.stderr, flush=True)
    if args.json:
        from servobench.bench.report.summary import print_json

        print_json({"error": message})
    return 130


def _print_text(result) -> None:
    from servobench.bench.fleet.table import CSV_FILE, PARQUET_FILE

    rows, failed, trends, out = result.rows, result.failed, result.axes, result.out_dir
    print(f"{len(rows)} logs, {len(failed)} failed; {len(trends)} axes, {len(result.flagged)} flagged")
    for t in result.flagged:
        print(f"FLAGGED {t.axis}: {'; '.join(t.reasons)}")
    for t in trends:
        for sentence in t.structure:
            print(f"note {t.axis}: {sentence}")
    for r in failed:
        print(f"failed {r.log}: {r.error.removeprefix(r.log + ': ')}")
    print(f"wrote {out / CSV_FILE}, {out / PARQUET_FILE}, {result.page}")
