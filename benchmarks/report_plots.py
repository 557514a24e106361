"""What the identification plots show, in figures: the friction map through sensor noise and the
friction bias of the differential FRF, over amplitudes; and what drawing them costs.

For the paper's plant (M 0.1, B 1, Coulomb 0.5 / 0.4) with velocity noise
``--noise`` and each amplitude, a SIDBE log is simulated, identified
(``auto``) and:

* friction map: the spread (std) of the raw sampled force ``u - M dv/dt - B v``
  against the median spread per velocity bin after the zero-phase filter, and
  the largest error of a bin mean (bins above a quarter of the top speed)
  against the plant's Coulomb level;
* FRF: the largest offset of the measured differential FRF from the linear
  block, and from the model simulated with its friction (the offset the plot
  explains), both relative; and whether the plot carries the bias note;
* the CPU time of ``write_plots`` (three PNGs).

Run: ``python benchmarks/report_plots.py [--noise 0.01] [--amplitudes 1,2,5,60]``
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from servobench.bench.identify.auto import identify  # noqa: E402
from servobench.bench.procedure.excitation import make_design  # noqa: E402
from servobench.bench.report.plot_data import frf_evidence, friction_map  # noqa: E402
from servobench.bench.report.plots import write_plots  # noqa: E402
from servobench.bench.testing.synthetic import simulate_experiment  # noqa: E402
from servobench.sim_backend.physics.plant import PlantParams  # noqa: E402
from servobench.units import ROTARY  # noqa: E402

TRUE = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)


def row(amplitude: float, noise: float, seed: int) -> dict:
    from dataclasses import replace

    log = simulate_experiment(TRUE.with_changes(noise=noise, seed=seed), make_design(amplitude, period_s=4.0,
                                                                                     periods=5))  # fmt: skip
    result = identify(replace(log, metadata={**log.metadata, **ROTARY.as_metadata()}))
    m, run = result.model, result.verification.runs[0]
    a = math.exp(-m.B * 1e-3 / m.M)
    raw = run.u[:-1] - (run.v[1:] - a * run.v[:-1]) * m.B / (1 - a)
    fm = friction_map(result)
    moving = np.abs(fm.v_centre) > 0.25 * np.max(np.abs(fm.v_centre))
    truth = np.where(fm.v_centre > 0, TRUE.coulomb_pos, -TRUE.coulomb_neg)
    ev = frf_evidence(result)
    with tempfile.TemporaryDirectory() as folder:
        t0 = time.process_time()
        write_plots(result, folder)
        cpu = time.process_time() - t0
    return {
        "A": amplitude,
        "method": result.method,
        "raw_std": float(np.std(raw)),
        "bin_std": float(np.median(fm.force_std[moving])),
        "bin_err": float(np.max(np.abs(fm.force_mean[moving] - truth[moving]))),
        "frf_off_linear": float(np.max(np.abs(ev.measured - ev.linear) / np.abs(ev.linear))),
        "frf_off_friction": float(np.max(np.abs(ev.measured - ev.with_friction) / np.abs(ev.measured))),
        "frf_2se": float(np.max(2 * ev.std_error / np.abs(ev.measured))),
        "note": ev.biased,
        "cpu_s": cpu,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--noise", type=float, default=0.01)
    p.add_argument("--amplitudes", default="1,2,5,60")
    p.add_argument("--seed", type=int, default=1)
    args = p.parse_args()
    print(f"plant M 0.1, B 1, Coulomb 0.5/0.4; velocity noise {args.noise}; 5 periods of 4 s at 1 kHz")
    print(f"{'A':>5} {'method':>6} | {'raw std':>8} {'bin std':>8} {'bin err':>8} | "
          f"{'FRF vs lin':>10} {'vs fric':>8} {'2 s.e.':>7} {'note':>5} | {'plots cpu':>9}")  # fmt: skip
    for amplitude in (float(a) for a in args.amplitudes.split(",")):
        r = row(amplitude, args.noise, args.seed)
        print(f"{r['A']:>5g} {r['method']:>6} | {r['raw_std']:8.3f} {r['bin_std']:8.3f} {r['bin_err']:8.3f} | "
              f"{100 * r['frf_off_linear']:9.1f}% {100 * r['frf_off_friction']:7.1f}% "
              f"{100 * r['frf_2se']:6.1f}% {'yes' if r['note'] else 'no':>5} | {r['cpu_s']:8.2f}s")  # fmt: skip


if __name__ == "__main__":
    main()
