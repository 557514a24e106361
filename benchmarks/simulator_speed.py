"""The compiled plant simulator against the reference loops, and the EMPS diagnosis it speeds up.

Per plant (the diagnosis benchmark's: the base, every library effect alone, drawn by
:func:`~servobench.bench.testing.hidden_effects.random_case`), the time per sample of the
reference Python loops (``RichModel(..., reference=True)``, ``simulate_coulomb``) and of the
compiled integrator on the same runs, best of several repeats, and the largest difference of
their velocities relative to its largest value. Then ``diagnose`` on the EMPS log
(24 841 samples) as the CLI runs it, each in a fresh process: cold (the kernels compiled in
an empty numba cache) and warm (compiled code loaded from the cache), beside the figure
before the compiled simulator (:data:`BEFORE_EMPS_S`).

Run: ``python benchmarks/simulator_speed.py [--samples 20000] [--repeats 5] [--no-emps | --emps-only]``
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from servobench.bench.testing.hidden_effects import random_case  # noqa: E402
from servobench.sim_backend.physics import effects as library  # noqa: E402
from servobench.sim_backend.physics.compiled import pack_coulomb, run  # noqa: E402
from servobench.sim_backend.physics.coulomb import PlantState, simulate_coulomb  # noqa: E402
from servobench.sim_backend.physics.effects import collect_terms  # noqa: E402
from servobench.sim_backend.physics.rich_plant import RichModel, build_model  # noqa: E402

EMPS = Path(__file__).resolve().parents[2] / "shared" / "data" / "emps" / "emps.csv"
FS_HZ = 500.0
#: ``servobench diagnose`` on EMPS before the compiled simulator [s, wall]: the issue's figure
#: on a quiet machine, and the same command measured on the 2-core machine of this change.
BEFORE_EMPS_S = {"issue 30, a quiet machine": 21.6, "the 2-core machine of this change": 12.2}


def command(rng: np.random.Generator, n: int, amplitude: float) -> np.ndarray:
    """A binary command with random levels and hold times, through stick and slip."""
    holds = rng.integers(20, 200, n // 20)
    levels = rng.choice([-1.0, 1.0], holds.size) * rng.uniform(0.3, 1.5, holds.size)
    return amplitude * np.repeat(levels, holds)[:n]


def best(fn, repeats: int) -> float:
    """The least CPU time [s] of this process over ``repeats`` calls (CPU time: the shared
    machine's other work lengthens the wall clock, not this)."""
    out = []
    for _ in range(repeats):
        t = time.process_time()
        fn()
        out.append(time.process_time() - t)
    return min(out)


def per_sample(samples: int, repeats: int) -> None:
    dt = 1.0 / FS_HZ
    print(
        f"per sample, {samples} samples from rest at {FS_HZ:g} Hz, best of {repeats} [CPU ns/sample]"
    )
    print(f"{'plant':<20}{'reference':>11}{'compiled':>10}{'faster':>8}{'max rel. diff':>15}")
    ratios = []
    for name in (None, *library.names()):
        rng = np.random.default_rng(1)
        params = random_case(name, rng).params
        u = command(rng, samples, 3.0 * max(params.coulomb_pos, params.coulomb_neg))
        if not params.effects:
            pk = pack_coulomb(params, dt)
            line = np.r_[0.0, u]

            def old(params=params, u=u):
                return simulate_coulomb(u, dt, params)[0]

            def new(pk=pk, line=line, u=u):
                return run([pk], [[line]], [(0, 0, u.size, 0)], np.zeros((1, 5)))[0][0]
        else:
            ref = RichModel(params, collect_terms(params), reference=True)
            model = build_model(params)

            def old(ref=ref, u=u):
                ref.reset()
                return ref.simulate(u, dt, PlantState())[0]

            def new(model=model, u=u):
                model.reset()
                return model.simulate(u, dt, PlantState())[0]

        new()  # compiled, or loaded from the cache
        t_old, t_new = best(old, max(1, repeats // 2)), best(new, repeats)
        v_old, v_new = old(), new()
        diff = float(np.max(np.abs(v_new - v_old)) / max(np.max(np.abs(v_old)), 1e-300))
        compiled = not params.effects or model.packed(dt) is not None
        ratio = t_old / t_new
        if params.effects and compiled:
            ratios.append(ratio)
        label = (name or "base") + ("" if compiled else " (ref.)")
        print(
            f"{label:<20}{1e9 * t_old / samples:>11.0f}{1e9 * t_new / samples:>10.1f}"
            f"{ratio:>7.0f}x{diff:>15.1e}"
        )
    print(f"compiled effects: {min(ratios):.0f}x to {max(ratios):.0f}x faster per sample")


def emps_seconds() -> None:
    if not EMPS.is_file():
        print(f"EMPS log not found ({EMPS.name}): skipped")
        return
    code = (
        "import time; t = time.perf_counter();"
        "from servobench.bench.diagnose.workflow import diagnose;"
        "from servobench.bench.log.io import read_log;"
        f"r = diagnose(read_log({str(EMPS)!r}));"
        "print(time.perf_counter() - t, r.verdict.verdict)"
    )
    print("diagnose on EMPS (24 841 samples), a fresh process each [s, wall]:")
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache}
        for label in ("cold (compiles)", "warm (cache)", "warm (cache)"):
            t = time.perf_counter()
            out = subprocess.run(
                [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
            )
            wall = time.perf_counter() - t
            inside, verdict = out.stdout.split()[-2:]
            print(
                f"  {label:<18}{wall:6.1f} s process, {float(inside):5.1f} s in diagnose ({verdict})"
            )
    for label, seconds in BEFORE_EMPS_S.items():
        print(f"  before the compiled simulator, {label}: {seconds:.1f} s process")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=20000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--no-emps", action="store_true", help="skip the EMPS diagnosis")
    parser.add_argument("--emps-only", action="store_true", help="only the EMPS diagnosis")
    args = parser.parse_args()
    if not args.emps_only:
        per_sample(args.samples, args.repeats)
    if not args.no_emps:
        emps_seconds()


if __name__ == "__main__":
    main()
