"""Confusion table of the discrepancy workflow over random hidden-effect plants.

For every library effect (and a control with nothing hidden) draws ``--cases``
random plants with that effect (:func:`servobench.bench.testing.hidden_effects.random_case`),
writes their logs, hands only the log to :func:`servobench.bench.diagnose.workflow.diagnose` and
tabulates the true effect against the first effect named ("none" when
nothing was named), with the median velocity gap before and after and the
smallest shrink factor. Cases run in ``--jobs`` worker processes.

Run: ``python benchmarks/diagnose.py [--cases 5] [--seed 1] [--jobs 2]``
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from servobench.bench.diagnose.workflow import diagnose  # noqa: E402
from servobench.bench.logio import read_log  # noqa: E402
from servobench.bench.testing.hidden_effects import random_case, write_case_log  # noqa: E402
from servobench.sim_backend.physics import effects as library  # noqa: E402

NONE = "none"


def run_case(effect: str | None, seed: int, folder: str) -> dict:
    rng = np.random.default_rng(seed)
    case = random_case(effect, rng)
    path = Path(folder) / f"{effect or NONE}-{seed}.csv"
    log = read_log(write_case_log(case, path, rng))
    t0 = time.process_time()
    d = diagnose(log)
    return {
        "true": effect or NONE,
        "seed": seed,
        "named": [e.name for e in d.effects],
        "before": d.gap_before,
        "after": d.gap_after,
        "cpu_s": time.process_time() - t0,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=5, help="random plants per effect")
    ap.add_argument("--seed", type=int, default=1, help="master seed")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes")
    args = ap.parse_args(argv)
    effects = [None, *library.names()]
    master = np.random.default_rng(args.seed)
    jobs = [(e, int(master.integers(2**31))) for e in effects for _ in range(args.cases)]
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as folder, ProcessPoolExecutor(args.jobs) as pool:
        results = list(pool.map(run_case, *zip(*jobs, strict=True), [folder] * len(jobs)))
    wall = time.perf_counter() - t0
    labels = [NONE, *library.names()]
    short = {n: n[:7] for n in labels}
    print(f"{len(results)} cases ({args.cases} per row), seed {args.seed}, {wall:.0f} s wall")
    print()
    corner = "true \\ named first"
    head = f"{corner:20s}" + "".join(f"{short[n]:>8s}" for n in labels)
    print(head + f"{'gap before':>12s}{'gap after':>11s}{'min shrink':>12s}{'cpu s':>7s}")
    correct = 0
    for true in labels:
        rows = [r for r in results if r["true"] == true]
        counts = {n: 0 for n in labels}
        for r in rows:
            counts[r["named"][0] if r["named"] else NONE] += 1
        correct += counts[true]
        before = np.median([r["before"] for r in rows])
        after = np.median([r["after"] for r in rows])
        shrink = min(r["before"] / r["after"] for r in rows)
        cpu = np.mean([r["cpu_s"] for r in rows])
        cells = "".join(f"{counts[n] or '.':>8}" for n in labels)
        print(f"{true:20s}{cells}{before:11.2f}%{after:10.2f}%{shrink:11.1f}x{cpu:7.1f}")
    print()
    extra = sum(1 for r in results if len(r["named"]) > 1)
    print(
        f"named first correctly: {correct}/{len(results)}; cases with more than one effect: {extra}"
    )
    for r in results:
        if (r["named"][0] if r["named"] else NONE) != r["true"] or len(r["named"]) > 1:
            named = ", ".join(r["named"]) or NONE
            print(
                f"  {r['true']} (seed {r['seed']}): named {named}; "
                f"gap {r['before']:.2f}% -> {r['after']:.2f}%"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
