"""Fleet: throughput on Dask for many SIDBE logs, the per-log overhead, and reading a 10^6-row log.

Targets: 2 workers at 1.7x or better the throughput of 1 worker on a
2-core machine; reading a 10^6-row log in under 0.5 s (the log reader's
figure, measured with whatever ``read_log`` is installed).

Prints:

- logs per second for ``--logs`` generated SIDBE logs (several axes, dated
  records, one axis wearing) on a local cluster of 1 and of 2 workers,
  the cluster already up (its start-up time is printed apart), and the
  speed-up of 2 workers over 1;
- the per-log overhead of the Dask path: (1-worker time - plain sequential
  loop time) / logs;
- the best of ``--repeat`` reads of a 10^6-row ``run,t,u,v,x`` log;
- the CPU time per log and the cores the workers obtained (their CPU time
  over the wall time), and the load average before and after each figure:
  other work on the machine lowers the throughput, and these say by how much;
  from them, the speed-up 2 workers reach on 2 idle cores (2 x the worker CPU
  time of 1 worker over that of 2 -- what the work itself scales by).

Run: ``python benchmarks/fleet.py [--logs 200] [--repeat 3]``
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from servobench.bench.fleet.engine import connect, run_on, run_sequential  # noqa: E402
from servobench.bench.fleet.sources import find_logs  # noqa: E402
from servobench.bench.log.io import LogWriter, read_log  # noqa: E402
from servobench.bench.testing.fleet_logs import AxisSpec, write_fleet  # noqa: E402


def load() -> str:
    one, five, _ = os.getloadavg()
    return f"load {one:.1f} (5 min {five:.1f})"


def fleet_logs(folder: Path, logs: int, period_s: float, periods: int) -> list:
    """``logs`` SIDBE logs: axes of 5 dated records, every fourth axis wearing."""
    records = 5
    axes = [
        AxisSpec(f"axis-{i:03d}", records=records, wear=0.4 if i % 4 == 0 else 0.0)
        for i in range(-(-logs // records))
    ]
    write_fleet(folder, axes, period_s=period_s, periods=periods)
    return find_logs([folder])[:logs]


def cpu_seconds() -> float:
    """CPU time [s] this process has used (user + system)."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def throughput(sources: list, workers: int) -> tuple[float, float, float, list]:
    """(cluster start [s], processing time [s], worker CPU time [s], rows) on ``workers``."""
    t0 = time.perf_counter()
    with connect(workers) as client:
        before = sum(client.run(cpu_seconds).values())
        t1 = time.perf_counter()
        rows = run_on(client, sources)
        t2 = time.perf_counter()
        cpu = sum(client.run(cpu_seconds).values()) - before
    return t1 - t0, t2 - t1, cpu, rows


def read_figure(folder: Path, rows: int, repeat: int) -> float:
    """Best time [s] to read a ``rows``-row two-run log."""
    path = folder / "big.csv"
    n = rows // 2
    rng = np.random.default_rng(0)
    with LogWriter(path, {"fs": 1000.0}) as writer:
        for run in (1, 2):
            t = np.arange(n) / 1000.0
            u = rng.choice([-1.0, 1.0], n)
            v = np.cumsum(u) * 1e-3
            writer.append_block(np.full(n, run), t, u, v, np.cumsum(v) * 1e-3)
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        log = read_log(path)
        best = min(best, time.perf_counter() - t0)
    assert sum(len(r) for r in log.runs) == 2 * n
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", type=int, default=200)
    ap.add_argument("--period", type=float, default=2.0, help="excitation period [s]")
    ap.add_argument("--periods", type=int, default=3)
    ap.add_argument("--rows", type=int, default=1_000_000, help="rows of the read benchmark")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        print(f"reading a {args.rows:,}-row log ({load()})")
        best = read_figure(folder, args.rows, args.repeat)
        print(f"  read_log: {best:.3f} s best of {args.repeat} (target < 0.5 s); {load()}")

        sources = fleet_logs(folder / "fleet", args.logs, args.period, args.periods)
        rows_per_log = 2 * int(round(args.period * 1000)) * args.periods
        print(f"\n{len(sources)} SIDBE logs of {rows_per_log} rows ({load()})")
        t0, c0 = time.perf_counter(), cpu_seconds()
        reference = run_sequential(sources)
        seq, seq_cpu = time.perf_counter() - t0, cpu_seconds() - c0
        print(f"  plain sequential loop: {seq:.2f} s, {len(sources) / seq:.2f} logs/s, "
              f"{seq_cpu / len(sources) * 1e3:.0f} ms CPU per log; {load()}")  # fmt: skip
        times, cpus = {}, {}
        for workers in (1, 2):
            start, took, cpu, rows = throughput(sources, workers)
            times[workers], cpus[workers] = took, cpu
            same = [r.record() for r in rows] == [r.record() for r in reference]
            print(
                f"  Dask, {workers} worker(s): {took:.2f} s, {len(sources) / took:.2f} logs/s, "
                f"{cpu / len(sources) * 1e3:.0f} ms worker CPU per log, {cpu / took:.2f} cores "
                f"obtained (cluster start {start:.1f} s; rows {'identical to' if same else 'DIFFER from'} "
                f"the sequential loop); {load()}"
            )
        print(f"  speed-up of 2 workers over 1: {times[1] / times[2]:.2f}x (target >= 1.7x)")
        print(f"  the same on 2 idle cores, from CPU time (2 x worker CPU on 1 / on 2): "
              f"{2 * cpus[1] / cpus[2]:.2f}x; the wall-clock figure reaches it when the "
              f"workers obtain 2 cores")  # fmt: skip
        overhead = (times[1] - seq) / len(sources)
        print(f"  per-log overhead of the Dask path: {overhead * 1e3:+.1f} ms "
              f"({100 * overhead / (seq / len(sources)):+.1f} % of {seq / len(sources) * 1e3:.0f} ms per log)")  # fmt: skip


if __name__ == "__main__":
    main()
