"""The paper's Table I, reproduced: SIDBE as published and the joint/auto estimator.

Plant: pole -10 1/s, DC gain 1 (M = 0.1, B = 1), Coulomb friction 0.5 (v > 0)
and 0.4 (v < 0), excited with the default SIDBE design at amplitudes ±1,
±60 and ±150. Part 1 is noise-free; part 2 adds white velocity-sensor noise
and prints the spread of the joint estimate over many seeds beside the
Cramér-Rao bound ``sigma^2 (J^T J)^-1`` of the output-error model (``J`` the
sensitivity of the simulated velocity to M, B, coulomb_pos, coulomb_neg).

Run: ``python benchmarks/table1.py [--seeds 50] [--noise 0.01] [--jobs 2]``
(``--noise`` is the velocity noise sigma as a fraction of the amplitude).
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from servobench.bench.identify.auto import identify  # noqa: E402
from servobench.bench.identify.output_error import Chunk, cramer_rao  # noqa: E402
from servobench.bench.model.servo import ServoModel  # noqa: E402
from servobench.bench.procedure.excitation import design_excitation, make_design  # noqa: E402
from servobench.bench.testing.synthetic import simulate_experiment  # noqa: E402
from servobench.sim_backend.physics.plant import PlantParams, simulate_coulomb  # noqa: E402

#: The paper's Table I: amplitude -> (pole [1/s], DC gain).
PAPER = {1.0: (-35.01, 0.1926), 60.0: (-10.2805, 0.96651), 150.0: (-10.0767, 0.98616)}
TRUE = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)
TRUE_MODEL = ServoModel(0.1, 1.0, 0.5, 0.4)
KEYS = ("pole", "dc_gain", "coulomb_pos", "coulomb_neg")
TRUTH = {"pole": -10.0, "dc_gain": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}


def _err(value: float, key: str) -> str:
    return f"{100 * (value / TRUTH[key] - 1):+.3f}%"


def noise_free(amplitudes: list[float]) -> None:
    print("Part 1 - noise-free (errors relative to the true plant)")
    head = f"{'amp':>5} {'method':<18} {'pole':>10} {'err':>9} {'DC gain':>9} {'err':>9} {'Fc+':>8} {'err':>9} {'Fc-':>8} {'err':>9} {'fit %':>8} {'time s':>7}"
    print(head)
    print("-" * len(head))
    for amp in amplitudes:
        log = simulate_experiment(TRUE, make_design(amp))
        if amp in PAPER:
            pole, gain = PAPER[amp]
            print(
                f"{amp:>5g} {'paper (Table I)':<18} {pole:>10.4f} {_err(pole, 'pole'):>9} {gain:>9.5f} {_err(gain, 'dc_gain'):>9}"
            )
        for method in ("sidbe", "joint", "auto"):
            t0 = time.perf_counter()
            r = identify(log, method)
            el = time.perf_counter() - t0
            m = r.model
            label = {
                "sidbe": "SIDBE as published",
                "joint": "joint",
                "auto": f"auto -> {r.method}",
            }[method]
            print(
                f"{amp:>5g} {label:<18} {m.pole:>10.4f} {_err(m.pole, 'pole'):>9} {m.dc_gain:>9.5f} "
                f"{_err(m.dc_gain, 'dc_gain'):>9} {m.coulomb_pos:>8.4f} {_err(m.coulomb_pos, 'coulomb_pos'):>9} "
                f"{m.coulomb_neg:>8.4f} {_err(m.coulomb_neg, 'coulomb_neg'):>9} {r.fit_percent:>8.3f} {el:>7.2f}"
            )
    print()


def _one(args: tuple[float, float, int]) -> dict[str, float]:
    amp, sigma, seed = args
    log = simulate_experiment(TRUE.with_changes(noise=sigma, seed=seed), make_design(amp))
    out = {}
    for method in ("joint", "sidbe"):
        m = identify(log, method).model
        out.update(
            {
                f"{method}.M": m.M,
                f"{method}.B": m.B,
                f"{method}.coulomb_pos": m.coulomb_pos,
                f"{method}.coulomb_neg": m.coulomb_neg,
            }
        )
    return out


def crb(amp: float, sigma: float) -> dict[str, float]:
    """Cramér-Rao bound for the whole log (both runs from rest, every sample)."""
    design = make_design(amp)
    exc = design_excitation(design)
    dt = 1.0 / design.fs_hz
    chunks = []
    for _, u in exc.runs():
        v, _, _ = simulate_coulomb(u, dt, TRUE)
        chunks.append(Chunk(u, v, dt))
    return cramer_rao(TRUE_MODEL, chunks, sigma)


def noisy(amplitudes: list[float], seeds: int, noise: float, jobs: int) -> None:
    print(f"Part 2 - velocity noise sigma = {noise:g} x amplitude, {seeds} seeds")
    head = (
        f"{'amp':>5} {'sigma':>7} {'param':<12} {'true':>7} {'joint mean':>11} {'bias/std':>9} "
        f"{'joint std':>10} {'CRB':>10} {'std/CRB':>8} {'SIDBE mean':>11} {'SIDBE std':>10}"
    )
    print(head)
    print("-" * len(head))
    for amp in amplitudes:
        sigma = noise * amp
        t0 = time.perf_counter()
        tasks = [(amp, sigma, seed) for seed in range(seeds)]
        if jobs > 1:
            with ProcessPoolExecutor(jobs) as pool:
                rows = list(pool.map(_one, tasks))
        else:
            rows = [_one(t) for t in tasks]
        bound = crb(amp, sigma)
        for key, true in (("M", 0.1), ("B", 1.0), ("coulomb_pos", 0.5), ("coulomb_neg", 0.4)):
            j = np.array([r[f"joint.{key}"] for r in rows])
            s = np.array([r[f"sidbe.{key}"] for r in rows])
            sd = j.std(ddof=1)
            print(
                f"{amp:>5g} {sigma:>7.3g} {key:<12} {true:>7.3g} {j.mean():>11.5g} "
                f"{(j.mean() - true) / (sd / np.sqrt(len(j))):>+9.2f} {sd:>10.3g} {bound[key]:>10.3g} "
                f"{sd / bound[key]:>8.2f} {s.mean():>11.5g} {s.std(ddof=1):>10.3g}"
            )
        print(
            f"      ({len(rows)} seeds in {time.perf_counter() - t0:.1f} s; bias/std = "
            "(mean - true) / standard error of the mean)"
        )
    print()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=50)
    p.add_argument("--noise", type=float, default=0.01, help="velocity noise sigma / amplitude")
    p.add_argument("--amplitudes", default="1,60,150")
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--no-noise-part", action="store_true")
    args = p.parse_args(argv)
    amps = [float(a) for a in args.amplitudes.split(",")]
    noise_free(amps)
    if not args.no_noise_part and args.seeds > 1:
        noisy(amps, args.seeds, args.noise, args.jobs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
