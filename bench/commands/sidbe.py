"""``servobench sidbe --drive URL``: the whole SIDBE procedure on a drive.

Designs the excitation, streams u1 and u2, identifies and verifies the
model, repeats with a larger amplitude (or a redesigned spectrum) while the
verification fit is below the threshold (step 6), and writes ``log.csv``,
``model.json`` and PNG plots to the output folder. On an axis with limited
travel (``--loop auto``, the default, with ``xmin``/``xmax`` in the URL) the
excitation runs in closed loop inside the window (``probe.csv`` first).

The verdict leads: the first line is ``PASS: ...`` when the verification
fit reached ``--fit-threshold``, else ``FAIL: ...`` (exit status 3); under
``--json`` the object's first key is ``verdict``. An axis that never moved
above the sensor noise gets no model: one error line (exit status 1).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from servobench.bench.commands.excitation_args import add_excitation_arguments, parse_freqs

#: Parent of the default output folders.
RUNS_DIR = "servobench-runs"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from servobench.bench.procedure.sidbe import DEFAULT_FIT_THRESHOLD, DEFAULT_MAX_ITERATIONS

    add_excitation_arguments(p)
    p.add_argument(
        "--method",
        choices=("auto", "sidbe", "joint"),
        default="auto",
        help="identification method (default auto: both, the better on held-out data)",
    )
    p.add_argument(
        "--fit-threshold",
        type=float,
        default=DEFAULT_FIT_THRESHOLD,
        metavar="PCT",
        help=f"verification fit [%%] that ends the procedure (default {DEFAULT_FIT_THRESHOLD:g})",
    )
    p.add_argument(
        "--max-iterations",
        type=int,
        default=DEFAULT_MAX_ITERATIONS,
        metavar="N",
        help=f"most excite-identify rounds of step 6 (default {DEFAULT_MAX_ITERATIONS})",
    )
    p.add_argument(
        "--max-amplitude",
        type=float,
        default=None,
        metavar="A",
        help="highest amplitude step 6 may use (default: the drive's max_u, else 8x --amplitude)",
    )
    p.add_argument("--resonance", action="store_true", help="let SIDBE fit a series resonance")
    p.add_argument("--no-plots", action="store_true", help="do not write PNG plots")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    p.add_argument(
        "--out",
        default=None,
        metavar="DIR",
        help=f"output folder, new or empty: a folder holding an earlier run is refused "
        f"(default: a new folder ./{RUNS_DIR}/<timestamp>)",
    )


def default_out_dir(base: Path | None = None) -> Path:
    """A new ``./servobench-runs/<YYYYmmdd-HHMMSS>[-n]`` folder name (the checkout's
    ``.gitignore`` lists ``servobench-runs/``)."""
    root = (base or Path.cwd()) / RUNS_DIR
    stamp = time.strftime("%Y%m%d-%H%M%S")
    path = root / stamp
    n = 1
    while path.exists():
        n += 1
        path = root / f"{stamp}-{n}"
    return path


def note_lowered_rate(requested_hz: float | None, drive) -> None:
    """Say on stderr when the default cycle rate was lowered to fit the drive's link."""
    import sys

    from servobench.bench.procedure.excitation import DEFAULT_FS_HZ
    from servobench.drivers.link_budget import drive_rate_hz, lowered_rate_note

    if requested_hz is None:
        chosen = drive_rate_hz(None, drive, DEFAULT_FS_HZ)
        note = lowered_rate_note(None, chosen, drive, DEFAULT_FS_HZ)
        if note:
            print(f"servobench: note: {note}", file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    from servobench.bench.commands.progress import stream_progress
    from servobench.bench.procedure.sidbe import (
        SidbeOptions,
        check_run_folder,
        loop_note,
        run_sidbe,
    )
    from servobench.bench.report.summary import print_json, print_result, rate_text
    from servobench.bench.run.runner import default_pace
    from servobench.drivers.registry import open_drive
    from servobench.errors import IdentificationError, add_note
    from servobench.verdict import Verdict

    options = SidbeOptions(
        amplitude=args.amplitude,
        ratio=args.ratio,
        fs_hz=args.fs,
        periods=args.periods,
        period_s=args.period,
        freqs_hz=parse_freqs(args.freqs),
        loop=args.loop,
        method=args.method,
        fit_threshold=args.fit_threshold,
        max_iterations=args.max_iterations,
        max_amplitude=args.max_amplitude,
        resonance=args.resonance,
        plots=not args.no_plots,
    )
    options.validate()
    out_dir = Path(args.out) if args.out else default_out_dir()
    check_run_folder(out_dir)  # before the drive is even opened
    drive = open_drive(args.drive)
    options.validate(drive)
    note_lowered_rate(args.fs, drive)
    with drive, stream_progress() as progress:
        if note := loop_note(options, drive):
            print(f"servobench: note: {note}", file=sys.stderr)
        try:
            result = run_sidbe(drive, options, out_dir, progress=progress)
        except IdentificationError as err:  # no model: say where the logs of the rounds are
            add_note(err, f"no model.json written; the logs are kept in {out_dir}")
            raise
    verdict = Verdict.of(result.passed)
    if args.json:
        print_json(result.to_json())
        return verdict
    print(verdict_line(result))
    rounds = ", ".join(
        f"#{it.index} ±{it.amplitude:g}: "
        + ("no model" if it.fit_percent is None else f"{it.fit_percent:.2f} %")
        for it in result.iterations
    )
    facts = {
        "cycle rate": rate_text(result.design.fs_hz, result.fs_achieved_hz, drive.max_rate_hz(),
                                pace=options.pace or drive.url.get_str("pace", "") or default_pace(drive)),
        "rounds (amplitude: fit)": rounds,
        "threshold": f"{result.fit_threshold:g} % ({'met' if result.passed else 'NOT met'})",
    }
    if result.hold is not None:
        h = result.hold
        facts["loop"] = (
            f"closed, {h['where']}-side hold at x = {h['x_ref']:.4g}, "
            + (f"{h['travel_share']:.0%} of the room {h['room']:.4g} used" if h["room"] is not None
               and math.isfinite(h["room"]) else "no travel window: the drive's hold keeps the axis where it stood")
        )
    if result.remarks:  # how the axis was stopped, optional objects the drive refused
        facts["drive remarks"] = "; ".join(result.remarks)
    print_result(result.result, "SIDBE: identified model", facts)
    print(f"output: {result.out_dir}")
    return verdict


def verdict_line(result) -> str:
    from servobench.verdict import Verdict

    """The first line: the verification fit against the threshold, and what to do on a fail."""
    fit, threshold = result.result.fit_percent, result.fit_threshold
    if result.passed:
        return Verdict.PASS.line(f"SIDBE verification fit {fit:.2f} % >= threshold {threshold:g} %")
    return Verdict.FAIL.line(
        f"SIDBE verification fit {fit:.2f} % < threshold {threshold:g} %; do not use this model before "
        f"the cause is found (servobench diagnose {result.log_path} names what the model lacks)"
    )
