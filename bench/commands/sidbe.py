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

from servobench.bench.commands.excitation_args import add_excitation_arguments, parse_freqs
from servobench.bench.procedure.run_folder import RUNS_DIR


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


def note(text: str) -> None:
    """A note for the user: one line on stderr."""
    print(f"servobench: note: {text}", file=sys.stderr)


def run(args: argparse.Namespace):
    from servobench.bench.commands.progress import stream_progress
    from servobench.bench.report.summary import print_json, print_result, rate_text
    from servobench.procedures import sidbe

    with stream_progress() as progress:
        result = sidbe(
            args.drive, args.out or None, amplitude=args.amplitude, ratio=args.ratio, fs_hz=args.fs,
            periods=args.periods, period_s=args.period, freqs_hz=parse_freqs(args.freqs), loop=args.loop,
            method=args.method, fit_threshold=args.fit_threshold, max_iterations=args.max_iterations,
            max_amplitude=args.max_amplitude, resonance=args.resonance, plots=not args.no_plots,
            progress=progress, note=note,
        )  # fmt: skip
    if args.json:
        print_json(result.to_dict())
        return result.verdict
    print(result.headline)
    run = result.details
    rounds = ", ".join(
        f"#{it.index} ±{it.amplitude:g}: "
        + ("no model" if it.fit_percent is None else f"{it.fit_percent:.2f} %")
        for it in result.iterations
    )
    facts = {
        "cycle rate": rate_text(run.design.fs_hz, run.fs_achieved_hz, result.link_max_hz, pace=result.pace),
        "rounds (amplitude: fit)": rounds,
        "threshold": f"{result.fit_threshold:g} % ({'met' if result.passed else 'NOT met'})",
    }
    if run.hold is not None:
        h = run.hold
        facts["loop"] = (
            f"closed, {h['where']}-side hold at x = {h['x_ref']:.4g}, "
            + (f"{h['travel_share']:.0%} of the room {h['room']:.4g} used" if h["room"] is not None
               and math.isfinite(h["room"]) else "no travel window: the drive's hold keeps the axis where it stood")
        )
    if run.remarks:  # how the axis was stopped, optional objects the drive refused
        facts["drive remarks"] = "; ".join(run.remarks)
    print_result(run.result, "SIDBE: identified model", facts)
    print(f"output: {result.out_dir}")
    return result.verdict
