"""Closed loop against open loop: bias and spread over noisy seeds, beside the Cramér-Rao bound.

An axis with a travel window is excited in closed loop under the hold loop
(:mod:`servobench.bench.run.closed`); the same excitation -- the same lines
and amplitude, so the same excitation power -- is applied in open loop to the
same axis with unlimited travel. Both go through the drive layer (``sim://``
with velocity noise, a new seed per run), are logged and identified by the
procedure's own estimator (``joint``: in closed loop the excitation is its
instrument and the output error runs on raw samples). The plan (lines,
amplitude, hold gains) is the one ``sidbe`` makes for the window, made once
from the true plant so that every seed gets the same excitation.

Printed per parameter: the mean, the bias in standard errors of the mean, the
spread (std over the seeds), the Cramér-Rao bound of the experiment
(``sigma^2 (J^T J)^-1``, ``J`` the sensitivity of the simulated velocity to
``M, B, coulomb_pos, coulomb_neg`` given the command applied, noise-free;
propagated to the pole and the DC gain), and their ratio. Then the share of
the window the hold used, and the travel the open-loop runs drifted over.

Run: ``python benchmarks/closed_loop.py [--plant sim|emps] [--seeds 50] [--noise 0.01] [--jobs 2]``
(``--noise`` is the velocity noise sigma in velocity units).
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from functools import cache
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from servobench.bench.identify.auto import identify  # noqa: E402
from servobench.bench.identify.output_error import Chunk, sensitivity  # noqa: E402
from servobench.bench.log.io import read_log  # noqa: E402
from servobench.bench.model.servo import ServoModel  # noqa: E402
from servobench.bench.procedure.excitation import design_excitation, make_design  # noqa: E402
from servobench.bench.run.closed import stream_closed_runs  # noqa: E402
from servobench.bench.run.hold import simulate_hold  # noqa: E402
from servobench.bench.run.runner import stream_runs  # noqa: E402
from servobench.bench.run.travel import ClosedLoopPlan, plan_closed_loop  # noqa: E402
from servobench.drivers.registry import open_drive  # noqa: E402
from servobench.sim_backend.physics.coulomb import simulate_coulomb  # noqa: E402

#: name -> (plant URL keys, true model, half window [position units], max_u)
PLANTS = {
    "sim": ("M=0.1&B=1&fc_pos=0.5&fc_neg=0.4", ServoModel(0.1, 1.0, 0.5, 0.4), 0.05, math.inf),
    "emps": ("M=95.1&B=203.5&fc_pos=17.2&fc_neg=23.6&units=linear",
             ServoModel(95.1, 203.5, 17.2, 23.6), 0.1, 300.0),
}  # fmt: skip
KEYS = ("M", "B", "coulomb_pos", "coulomb_neg", "pole", "dc_gain")


@cache
def make_plan(model: ServoModel, half: float, max_u: float) -> ClosedLoopPlan:
    """The plan sidbe makes for the window (amplitude from twice the friction, as it does)."""
    amplitude = 2.0 * max(model.coulomb_pos, model.coulomb_neg)
    cap = 0.8 * max_u if math.isfinite(max_u) else 8.0 * amplitude
    return plan_closed_loop(model, make_design(amplitude), half, where="host", x_ref=0.0,
                            max_u=max_u, cap=cap)  # fmt: skip


def _values(model: ServoModel) -> dict[str, float]:
    return {"M": model.M, "B": model.B, "coulomb_pos": model.coulomb_pos,
            "coulomb_neg": model.coulomb_neg, "pole": model.pole, "dc_gain": model.dc_gain}  # fmt: skip


def one(task: tuple[str, str, float, int]) -> dict[str, float]:
    """One seed: the closed-loop and the open-loop experiment, identified."""
    loop, plant, sigma, seed = task
    keys, model, half, max_u = PLANTS[plant]
    plan = make_plan(model, half, max_u)
    runs = design_excitation(plan.design).runs()
    url = f"sim://?{keys}&noise={sigma}&seed={seed}" + (f"&max_u={max_u}" if math.isfinite(max_u) else "")
    with tempfile.TemporaryDirectory() as d:
        log = Path(d) / "log.csv"
        if loop == "closed":
            with open_drive(url + f"&xmin={-half}&xmax={half}") as drive:
                res = stream_closed_runs(drive, runs, plan.design.fs_hz, log, plan,
                                         metadata=plan.design.metadata())  # fmt: skip
            travel = res.share
        else:
            with open_drive(url) as drive:
                stream_runs(drive, runs, plan.design.fs_hz, log,
                            metadata={**plan.design.metadata(), "loop": "open"})  # fmt: skip
            x = np.concatenate([r.x for r in read_log(log).runs])
            travel = float(np.max(np.abs(x))) / half
        data = read_log(log)
        u_rms = float(np.sqrt(np.mean(np.concatenate([r.u for r in data.runs]) ** 2)))
        result = identify(data, "joint")
    return {**_values(result.model), "travel": travel, "u_rms": u_rms}


def crb(loop: str, plant: str, sigma: float) -> dict[str, float]:
    """Cramér-Rao bound (1 sigma) of both runs from rest, noise-free, given the command applied."""
    _, model, half, max_u = PLANTS[plant]
    plan = make_plan(model, half, max_u)
    chunks = []
    for _, u_exc in design_excitation(plan.design).runs():
        if loop == "closed":
            r = simulate_hold(model, plan.controller, u_exc)
            u, v = r.u, r.v
        else:
            u = u_exc
            v, _, _ = simulate_coulomb(u, 1.0 / plan.design.fs_hz, model.to_plant_params())
        chunks.append(Chunk(u, v, 1.0 / plan.design.fs_hz))
    J = sensitivity(model, chunks)
    cov = sigma**2 * np.linalg.inv(J.T @ J)
    # pole = -B/M, dc_gain = 1/B: first-order propagation
    g_pole = np.array([model.B / model.M**2, -1.0 / model.M, 0.0, 0.0])
    g_gain = np.array([0.0, -1.0 / model.B**2, 0.0, 0.0])
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return {"M": sd[0], "B": sd[1], "coulomb_pos": sd[2], "coulomb_neg": sd[3],
            "pole": math.sqrt(g_pole @ cov @ g_pole), "dc_gain": math.sqrt(g_gain @ cov @ g_gain)}  # fmt: skip


def report(loop: str, rows: list[dict[str, float]], bound: dict[str, float], truth: ServoModel) -> None:
    true = _values(truth)
    for key in KEYS:
        x = np.array([r[key] for r in rows])
        sd = x.std(ddof=1)
        print(
            f"{loop:<7} {key:<12} {true[key]:>10.5g} {x.mean():>11.6g} "
            f"{100 * (x.mean() / true[key] - 1):>+8.3f}% {(x.mean() - true[key]) / (sd / math.sqrt(len(x))):>+8.2f} "
            f"{sd:>10.3g} {bound[key]:>10.3g} {sd / bound[key]:>8.2f} {100 * np.max(np.abs(x / true[key] - 1)):>8.3f}%"
        )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--plant", choices=sorted(PLANTS), default="sim")
    p.add_argument("--seeds", type=int, default=50)
    p.add_argument("--noise", type=float, default=0.01, help="velocity noise sigma [velocity units]")
    p.add_argument("--jobs", type=int, default=2)
    args = p.parse_args(argv)
    keys, model, half, max_u = PLANTS[args.plant]
    plan = make_plan(model, half, max_u)
    d, g = plan.design, plan.controller.gains
    print(f"plant {args.plant} ({keys}), window +-{half:g}, velocity noise sigma {args.noise:g}, {args.seeds} seeds")
    print(f"excitation: amplitude {d.amplitude:.4g}, lines {d.freqs_hz[0]:g}-{d.freqs_hz[-1]:g} Hz "
          f"({len(d.freqs_hz)}), {d.periods} periods of {d.period_s:g} s per run; hold loop kp {g.kp:.4g}, "
          f"ki {g.ki:.4g}, kd {g.kd:.4g} ({g.bandwidth_hz:g} Hz); predicted travel "
          f"{100 * plan.predicted / half:.1f} % of the half window")  # fmt: skip
    head = (f"{'loop':<7} {'param':<12} {'true':>10} {'mean':>11} {'bias':>9} {'bias/se':>8} "
            f"{'std':>10} {'CRB':>10} {'std/CRB':>8} {'worst':>9}")  # fmt: skip
    print(head)
    print("-" * len(head))
    travels = {}
    for loop in ("closed", "open"):
        t0 = time.perf_counter()
        tasks = [(loop, args.plant, args.noise, seed) for seed in range(args.seeds)]
        if args.jobs > 1:
            with ProcessPoolExecutor(args.jobs) as pool:
                rows = list(pool.map(one, tasks))
        else:
            rows = [one(t) for t in tasks]
        report(loop, rows, crb(loop, args.plant, args.noise), model)
        travels[loop] = (np.array([r["travel"] for r in rows]), np.mean([r["u_rms"] for r in rows]),
                         time.perf_counter() - t0)  # fmt: skip
    print()
    for loop, (share, u_rms, took) in travels.items():
        what = "share of the half window used" if loop == "closed" else "travel over the half window (no window)"
        print(f"{loop:<7} {what}: mean {100 * share.mean():.1f} %, max {100 * share.max():.1f} %; "
              f"rms total command {u_rms:.4g}; {took:.0f} s")
    print("(bias/se = (mean - true) / standard error of the mean; worst = largest error over the seeds)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
