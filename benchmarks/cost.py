"""Cost: identification time for 10^6 samples, and the simulated drive's speed in batch mode.

Targets: identifying 10^6 samples in under 1 s; the simulated drive at
>= 1000x real time in batch mode. Prints wall times (best of ``--repeat``)
for several cases, so the figure that meets a target is visible beside the
ones that do not.

Run: ``python benchmarks/cost.py [--samples 1000000] [--repeat 3]``
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from servobench.bench.identify.auto import identify  # noqa: E402
from servobench.bench.log.io import ExperimentLog, RunData, read_log  # noqa: E402
from servobench.bench.procedure.excitation import design_excitation, make_design  # noqa: E402
from servobench.bench.run.runner import stream_runs  # noqa: E402
from servobench.bench.testing.synthetic import simulate_experiment  # noqa: E402
from servobench.drivers.registry import open_drive  # noqa: E402
from servobench.sim_backend.physics.plant import PlantParams, simulate_coulomb  # noqa: E402

TRUE = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)


def best_of(repeat: int, fn) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def periodic_log(samples: int, amplitude: float, noise: float) -> ExperimentLog:
    """A two-run SIDBE log with ``samples`` samples in total (4 s periods at 1 kHz)."""
    periods = max(2, samples // 2 // 4000)
    design = make_design(amplitude, periods=periods)
    return simulate_experiment(TRUE.with_changes(noise=noise * amplitude, seed=1), design)


def random_steps_log(samples: int, noise: float) -> ExperimentLog:
    """One run of random command steps (not periodic: no period averaging possible)."""
    rng = np.random.default_rng(2)
    u = np.repeat(rng.uniform(-3, 3, samples // 250 + 1), 250)[:samples]
    v, x, _ = simulate_coulomb(u, 1e-3, TRUE)
    v = v + rng.normal(0, noise, samples) if noise else v
    t = np.arange(samples) * 1e-3
    return ExperimentLog((RunData(1, t, u, v, x),), {"fs": "1000", "loop": "open"}, 1000.0)


def identification(samples: int, repeat: int) -> None:
    print(f"Identification of {samples:,} samples (in memory; wall time, best of {repeat})")
    cases = [
        ("SIDBE log, noise-free, joint", periodic_log(samples, 1.0, 0.0), "joint"),
        ("SIDBE log, noise-free, auto", periodic_log(samples, 1.0, 0.0), "auto"),
        ("SIDBE log, noise 1 %, joint", periodic_log(samples, 1.0, 0.01), "joint"),
        ("SIDBE log, noise 1 %, auto", periodic_log(samples, 1.0, 0.01), "auto"),
        ("SIDBE log, noise 1 %, sidbe", periodic_log(samples, 1.0, 0.01), "sidbe"),
        ("random steps, noise-free, joint", random_steps_log(samples, 0.0), "joint"),
        ("random steps, noise 0.01, joint", random_steps_log(samples, 0.01), "joint"),
    ]
    for label, log, method in cases:
        n = sum(len(r) for r in log.runs)
        el, r = best_of(repeat, lambda log=log, method=method: identify(log, method))
        m = r.model
        flag = "OK " if el < 1.0 else "   "
        print(
            f"  {flag}{label:<34} {n:>9,} samples {el:7.3f} s   pole {m.pole:9.4f}  "
            f"Fc+ {m.coulomb_pos:.4f}  Fc- {m.coulomb_neg:.4f}  fit {r.fit_percent:7.3f} %"
        )
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "big.csv"
        with open_drive("sim://") as drive:
            exc = design_excitation(make_design(1.0, periods=max(2, samples // 2 // 4000)))
            stream_runs(drive, exc.runs(), 1000.0, path, metadata=exc.design.metadata())
        el, log = best_of(1, lambda: read_log(path))
        print(
            f"  (reading the same amount from CSV: {el:.2f} s for {sum(len(r) for r in log.runs):,} rows)"
        )
    print()


def drive_speed(seconds: float) -> None:
    cycles = int(seconds * 1000)
    print(f"Simulated drive, batch mode: {cycles:,} cycles at 1 kHz ({seconds:g} s of drive time)")
    u = design_excitation(make_design(1.0, periods=max(2, cycles // 4000))).u1[:cycles]
    with open_drive("sim://") as drive:
        drive.set_cycle(1e-3)
        drive.enable()
        t0 = time.perf_counter()
        for start in range(0, len(u), 2000):
            drive.exchange_block(u[start : start + 2000])
        el = time.perf_counter() - t0
    print(f"  drive.exchange_block alone:       {el:6.2f} s -> {seconds / el:7.0f}x real time")
    with tempfile.TemporaryDirectory() as tmp, open_drive("sim://") as drive:
        t0 = time.perf_counter()
        stream_runs(drive, [(1, u)], 1000.0, Path(tmp) / "log.csv")
        el = time.perf_counter() - t0
    print(f"  stream_runs with the CSV log:     {el:6.2f} s -> {seconds / el:7.0f}x real time")
    print()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--samples", type=int, default=1_000_000)
    p.add_argument("--repeat", type=int, default=3)
    args = p.parse_args(argv)
    identification(args.samples, args.repeat)
    drive_speed(args.samples / 1000.0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
