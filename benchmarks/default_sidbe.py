"""``servobench sidbe`` with default options through every served transport (issue 10 §4).

Each transport serves the simulated drive (M = 0.1, B = 1, Coulomb 0.5 / 0.4,
noise-free) in its own process (``servobench serve-sim``); the host runs
``servobench sidbe --drive URL --json`` with nothing else given, so the cycle
rate is the one the link carries (``Drive.max_rate_hz()`` with the default
margin) and the excitation is the default one (4 periods of 4 s per run, two
runs: 32 s of streaming at any rate). Printed per transport: the link's limit,
the rate chosen and achieved, the wall time of the whole command beside the
nominal streaming time, and the identified parameters' error against the
plant. Transports run one after the other, so they do not share the CPU.

Run: ``python benchmarks/default_sidbe.py [--transports serial,modbus-rtu]``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from servobench.bench.log.io import read_log
from servobench.bench.procedure.excitation import DEFAULT_PERIOD_S, DEFAULT_PERIODS
from servobench.bench.testing.served import ServedSim
from servobench.sim_backend.servers.serve import TRANSPORTS

PLANT = {"M": 0.1, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}
SIM = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"
#: Nominal streaming time of the default excitation: two runs [s].
NOMINAL_S = 2 * DEFAULT_PERIODS * DEFAULT_PERIOD_S


def one(transport: str, out: Path) -> dict[str, object]:
    """Run the default sidbe through ``transport``; its figures."""
    with ServedSim(transport, SIM) as served:
        t0 = time.monotonic()
        proc = subprocess.run(
            [sys.executable, "-m", "servobench", "sidbe", "--drive", served.url, "--json",
             "--no-plots", "--out", str(out)],
            capture_output=True, text=True, timeout=NOMINAL_S + 300,
        )  # fmt: skip
        wall_s = time.monotonic() - t0
    if proc.returncode != 0:
        return {"transport": transport, "error": proc.stderr.strip()}
    model = json.loads(proc.stdout)
    meta = read_log(out / "log.csv").metadata
    errors = {k: 100 * abs(model[k] / true - 1) for k, true in PLANT.items()}
    return {
        "transport": transport,
        "link_hz": meta.get("link_max_rate_hz", "-"),  # "-": the driver logs no limit
        "fs": model["fs"],
        "achieved": model["fs_achieved"],
        "wall_s": wall_s,
        "max_err_pct": max(errors.values()),
        "errors": errors,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--transports", default=",".join(sorted(TRANSPORTS)))
    args = ap.parse_args()
    print(f"default excitation: {NOMINAL_S:g} s of streaming (2 runs x {DEFAULT_PERIODS} x {DEFAULT_PERIOD_S:g} s)")
    print(f"{'transport':<11} {'link [Hz]':>9} {'fs [Hz]':>8} {'achieved':>9} {'wall [s]':>9} "
          f"{'M err %':>9} {'B err %':>9} {'Fc+ err %':>9} {'Fc- err %':>9}")  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        for transport in args.transports.split(","):
            r = one(transport, Path(tmp) / transport)
            if "error" in r:
                print(f"{transport:<11} failed: {r['error']}")
                continue
            e = r["errors"]
            print(
                f"{transport:<11} {r['link_hz']:>9} {r['fs']:>8g} {r['achieved']:>9.2f} {r['wall_s']:>9.1f} "
                f"{e['M']:>9.1e} {e['B']:>9.1e} {e['coulomb_pos']:>9.1e} {e['coulomb_neg']:>9.1e}"
            )


if __name__ == "__main__":
    main()
