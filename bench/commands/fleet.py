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
    from pathlib import Path

    from servobench.bench.fleet.engine import FleetInterrupted, require_fleet_extra
    from servobench.bench.fleet.sources import find_logs
    from servobench.bench.fleet.trend import axis_trends
    from servobench.errors import UsageError

    require_fleet_extra()
    axis_trends([], args.threshold)  # checks the threshold before any work
    if args.workers is not None and args.workers < 1:
        raise UsageError(f"--workers must be >= 1, got {args.workers}")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} is a file; name a folder")
    sources = find_logs(args.logs)
    out.mkdir(parents=True, exist_ok=True)
    try:
        rows, trends, figures = _on_cluster(args, sources, out)
    except FleetInterrupted as stop:
        _write_tables(stop.rows, out)
        done = sum(1 for r in stop.rows if not r.error.startswith("not processed"))
        return _interrupted(
            f"interrupted; Dask cluster shut down; {done} of {len(sources)} logs done, "
            f"kept in {out / 'fleet.csv'}",
            args,
        )
    except KeyboardInterrupt:
        return _interrupted("interrupted; Dask cluster shut down, nothing written", args)
    try:
        return _report(rows, trends, figures, out, args)
    except KeyboardInterrupt:
        return _interrupted(f"interrupted while writing {out}; run fleet again", args)


def _interrupted(message: str, args: argparse.Namespace) -> int:
    """Ctrl-C: one line on stderr (and ``{"error": ...}`` on stdout under ``--json``); 130."""
    print(f"servobench: {message}", file=sys.stderr, flush=True)
    if args.json:
        from servobench.bench.report.summary import print_json

        print_json({"error": message})
    return 130


def _on_cluster(args: argparse.Namespace, sources, out) -> tuple:
    """Rows (written at once to the tables), trends and each axis's figure, on the cluster."""
    from servobench.bench.commands.progress import count_progress
    from servobench.bench.fleet.engine import (
        FleetInterrupted,
        connect,
        map_on,
        run_on,
        worker_count,
    )
    from servobench.bench.fleet.page import axis_figure
    from servobench.bench.fleet.trend import axis_trends

    with connect(args.workers, args.scheduler) as client:
        print(f"servobench fleet: {len(sources)} logs on {worker_count(client)} Dask workers "
              f"(scheduler {client.scheduler.address})", file=sys.stderr, flush=True)  # fmt: skip
        with count_progress(f"identifying {len(sources)} logs", len(sources)) as progress:
            rows = run_on(client, sources, args.diagnose, progress)
        _write_tables(rows, out)
        trends = axis_trends(rows, args.threshold)
        try:
            figures = map_on(client, axis_figure, trends, threshold_percent=args.threshold)
        except KeyboardInterrupt:
            raise FleetInterrupted(rows) from None
    return rows, trends, figures


def _write_tables(rows, out) -> None:
    from servobench.bench.fleet.table import CSV_FILE, PARQUET_FILE, write_csv, write_parquet

    write_csv(rows, out / CSV_FILE)
    write_parquet(rows, out / PARQUET_FILE)


def _report(rows, trends, figures, out, args: argparse.Namespace) -> int:
    from servobench.bench.fleet.page import write_page
    from servobench.bench.report.summary import print_json

    page = write_page(rows, trends, args.threshold, out, figures)
    failed = [r for r in rows if not r.ok]
    if args.json:
        print_json(
            {"logs": len(rows), "failed": len(failed), "axes": [t.to_json() for t in trends]}
        )
    else:
        _print_text(rows, failed, trends, out, page)
    return 1 if failed else 0


def _print_text(rows, failed, trends, out, page) -> None:
    flagged = [t for t in trends if t.flagged]
    print(f"{len(rows)} logs, {len(failed)} failed; {len(trends)} axes, {len(flagged)} flagged")
    for t in flagged:
        print(f"FLAGGED {t.axis}: {'; '.join(t.reasons)}")
    for t in trends:
        for sentence in t.structure:
            print(f"note {t.axis}: {sentence}")
    for r in failed:
        print(f"failed {r.log}: {r.error.removeprefix(r.log + ': ')}")
    print(f"wrote {out / 'fleet.csv'}, {out / 'fleet.parquet'}, {page}")
