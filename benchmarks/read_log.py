"""Reading a 10^6-row log: wall time of ``read_log`` by number reader.

Target (issue 14): under 0.5 s for 10^6 rows. The log is the one
``benchmarks/cost.py`` streams from the simulated drive (``run,t,u,v,x,t_host``,
about 50 MB); the same rows are also written with ``;`` and decimal commas.
Prints the best of ``--repeat`` wall times and the process CPU time, for
the automatic choice (pyarrow for large tables when installed, the
``fleet`` extra) and for each engine forced.

Run: ``python benchmarks/read_log.py [--rows 1000000] [--repeat 3]``
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from servobench.bench.log import table as logtable  # noqa: E402
from servobench.bench.log.io import parse_log_text, read_log  # noqa: E402
from servobench.bench.procedure.excitation import design_excitation, make_design  # noqa: E402
from servobench.bench.run.runner import stream_runs  # noqa: E402
from servobench.drivers.registry import open_drive  # noqa: E402

TARGET_S = 0.5


def timed(repeat: int, fn) -> tuple[float, float, object]:
    best_wall, best_cpu, out = float("inf"), float("inf"), None
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        out = fn()
        best_wall = min(best_wall, time.perf_counter() - w)
        best_cpu = min(best_cpu, time.process_time() - c)
    return best_wall, best_cpu, out


def write_log(path: Path, rows: int) -> None:
    with open_drive("sim://") as drive:
        exc = design_excitation(make_design(1.0, periods=max(2, rows // 2 // 4000)))
        stream_runs(drive, exc.runs(), 1000.0, path, metadata=exc.design.metadata())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    have_pyarrow = logtable._pyarrow_csv() is not None
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "big.csv"
        write_log(path, args.rows)
        data = path.read_bytes()
        lines = data.split(b"\n")
        semi = b"\n".join(ln if ln.startswith(b"#") else ln.replace(b",", b";").replace(b".", b",") for ln in lines)
        (Path(tmp) / "semi.csv").write_bytes(semi)
        size_mb = len(data) / 1e6
        print(f"Reading a log of {args.rows:,} rows ({size_mb:.0f} MB), best of {args.repeat}; "
              f"target < {TARGET_S} s; pyarrow {'installed' if have_pyarrow else 'NOT installed'}")
        cases = [("read_log, automatic choice", lambda: read_log(path)),
                 ("read_log, ';' and decimal commas", lambda: read_log(Path(tmp) / "semi.csv"))]
        for engine in logtable.ENGINES:
            if engine == "pyarrow" and not have_pyarrow:
                continue
            cases.append((f"engine {engine} forced", lambda e=engine: parse_log_text(data, engine=e)))
        for label, fn in cases:
            wall, cpu, log = timed(args.repeat, fn)
            rows = sum(len(r) for r in log.runs)
            flag = "OK " if wall < TARGET_S else "   "
            print(f"  {flag}{label:<36} {wall:6.3f} s wall  {cpu:6.3f} s CPU  ({rows:,} rows)")


if __name__ == "__main__":
    main()
