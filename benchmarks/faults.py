"""Faults, bad input and load: what survives, what crashes, what memory a long run takes.

Prints, per transport, the faults injected (every case of
:data:`servobench.bench.testing.fault_scenarios.CASES`, plus the host killed) against the
faults survived (the run rode through or ended with the expected one-line
error, the drive ended with its torque off by its own state report, the log
kept every sample before the fault intact and marked incomplete); fuzz cases
run against crashes for each parser; and the peak memory growth of a long
run through ``sim://`` and through a served CANopen drive.

Run: ``python benchmarks/faults.py [--served-samples 1000000] [--fuzz 2000]``
(10^6 samples across the process boundary take about 7 minutes; pass
``--served-samples 0`` to skip them).
"""

from __future__ import annotations

import argparse
import copy
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np
import psutil

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from servobench.bench.log.io import parse_log_text  # noqa: E402
from servobench.bench.run.runner import stream_runs  # noqa: E402
from servobench.bench.testing.fault_scenarios import (  # noqa: E402
    CASES,
    HOST_KEYS,
    SERVE_ARGS,
    SIM_URL,
    judge,
    run_case,
    wait_for_state,
)
from servobench.bench.testing.served import ServedSim  # noqa: E402
from servobench.drivers.modbus.regmap import parse_map, resolve_map  # noqa: E402
from servobench.drivers.registry import BACKENDS, open_drive, resolve  # noqa: E402
from servobench.drivers.serial.ascii_line import decode_reply  # noqa: E402
from servobench.drivers.serial.dialect import dialect_path, load_dialect, parse_dialect  # noqa: E402
from servobench.errors import ServobenchError  # noqa: E402
from servobench.sim_backend.faults.spec import TRANSPORTS  # noqa: E402

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

KILL_HOST = """
import sys, numpy as np
from servobench.bench.run.runner import stream_runs
from servobench.drivers.registry import open_drive
u = np.tile(np.where((np.arange(160) // 20) % 2 == 0, 1.0, -1.0), 20)
def progress(done, total):
    if done >= 60 and not progress.said:
        progress.said = print("streaming", flush=True) or True
progress.said = False
with open_drive(sys.argv[1]) as drive:
    stream_runs(drive, [(1, u)], 1000.0, sys.argv[2], pace="real", progress=progress)
"""


# ------------------------------------------------------------------ faults
def kill_case(transport: str, work: Path) -> bool:
    """Kill a streaming host: the drive's watchdog must fault the axis, the log must read back."""
    from servobench.bench.log.io import read_log

    state, log = work / f"kill-{transport}.json", work / f"kill-{transport}.csv"
    args = [*SERVE_ARGS[transport], "--state-file", str(state)]
    with ServedSim(transport, SIM_URL, args) as served:
        host = subprocess.Popen(
            [sys.executable, "-c", KILL_HOST, served.url + HOST_KEYS + "&watchdog=0.2", str(log)],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        )  # fmt: skip
        ok = host.stdout.readline().strip() == "streaming"
        host.send_signal(signal.SIGKILL)
        host.wait()
        host.stdout.close()
        report = wait_for_state(state, ("fault",))
    parsed = read_log(log)
    return (
        ok
        and report.get("state") == "fault"
        and report.get("torque_off") is True
        and not parsed.complete
        and len(parsed.runs[0]) >= 60
    )


def faults(work: Path) -> None:
    print("Faults injected against faults survived (axis stopped, log intact, clear error)")
    print(f"  {'transport':11s} {'injected':>8s} {'survived':>8s}  {'rode through':>12s}  failures")
    for transport in TRANSPORTS:
        reference = run_case(None, transport, work)
        cases = [c for c in CASES if c.transport == transport]
        survived, rides, failures = 0, 0, []
        for case in cases:
            problems = judge(run_case(case, transport, work), reference)
            survived += not problems
            rides += case.rides and not problems
            failures += [f"{case.spec}: {p}" for p in problems]
        killed = kill_case(transport, work)
        survived += killed
        if not killed:
            failures.append("host killed: the drive did not stop by itself")
        print(
            f"  {transport:11s} {len(cases) + 1:8d} {survived:8d}  {rides:12d}  "
            + ("; ".join(failures) or "none")
        )


# -------------------------------------------------------------------- fuzz
def _mutate(rng: np.random.Generator, text: str, edits: int = 3) -> str:
    chars = list(text)
    alphabet = list("0123456789.,-+e#=\n\r tuvx\x00é\u2028") + ["nan", "inf", "1e999"]
    for _ in range(int(rng.integers(1, edits + 1))):
        i = int(rng.integers(0, len(chars) + 1))
        op = rng.integers(0, 3)
        if op == 0 and chars:
            del chars[min(i, len(chars) - 1)]
        elif op == 1:
            chars.insert(i, str(rng.choice(alphabet)))
        elif chars:
            chars[min(i, len(chars) - 1)] = str(rng.choice(alphabet))
    return "".join(chars)


def _damage(rng: np.random.Generator, doc: dict) -> dict:
    doc = copy.deepcopy(doc)
    values = [0, -1, 70000, 1.5, float("nan"), "", "x", "{bogus}", True, [], {}, [1, "a"]]
    for _ in range(int(rng.integers(1, 4))):
        table = doc
        while isinstance(table, dict) and table and rng.random() < 0.6:
            key = list(table)[int(rng.integers(0, len(table)))]
            if not isinstance(table[key], dict):
                break
            table = table[key]
        if not isinstance(table, dict) or not table:
            continue
        key = list(table)[int(rng.integers(0, len(table)))]
        if rng.random() < 0.3:
            del table[key]
        else:
            table[key] = values[int(rng.integers(0, len(values)))]
    return doc


def _url(rng: np.random.Generator) -> str:
    scheme = sorted(BACKENDS)[int(rng.integers(0, len(BACKENDS)))]
    keys = sorted(resolve(scheme).query_keys | {"max_u", "watchdog", "pace", "bogus"})
    values = ["1", "-1", "0", "abc", "1e999", "0x10", "servobench-sim", "odrive", "/", "", "%0A"]
    query = {str(rng.choice(keys)): str(rng.choice(values)) for _ in range(int(rng.integers(0, 5)))}
    host = str(rng.choice(["", "127.0.0.1", "vcan0", "[::1", "h:99999", "h:x"]))
    path = str(rng.choice(["", "/dev/ttyUSB0", "/x"]))
    return f"{scheme}://{host}{path}?" + "&".join(f"{k}={v}" for k, v in query.items())


def fuzz(cases: int) -> None:
    """Random and mutated inputs for each parser; a crash is any other exception or a
    message of more than one line."""
    rng = np.random.default_rng(7)
    log = "# fs = 1000\nrun,t,u,v,x\n1,0,1,0,0\n1,0.001,1,0.01,0.00001\n# status = complete\n"
    shipped_map = tomllib.loads(resolve_map("servobench-sim").read_text(encoding="utf-8"))
    shipped_dialect = tomllib.loads(dialect_path("odrive").read_text(encoding="utf-8"))
    odrive = load_dialect("odrive")
    targets = {
        "log reader": lambda: parse_log_text(_mutate(rng, log, 6)),
        "drive URLs": lambda: open_drive(_url(rng)),
        "register maps": lambda: parse_map(_damage(rng, shipped_map), "fuzz"),
        "dialects": lambda: parse_dialect(_damage(rng, shipped_dialect), "fuzz"),
        "serial replies": lambda: odrive.parse_reply(
            "feedback", decode_reply(_mutate(rng, "0.500000 1.250000").encode("utf-8"), False)
        ),
    }
    print(f"\nFuzz cases run against crashes ({cases} per parser)")
    for name, target in targets.items():
        outcome: Counter[str] = Counter()
        for _ in range(cases):
            try:
                target()
                outcome["accepted"] += 1
            except ServobenchError as err:
                outcome["typed error" if len(str(err).splitlines()) == 1 else "crash"] += 1
            except Exception:  # noqa: BLE001 -- counting exactly these
                outcome["crash"] += 1
        print(
            f"  {name:15s} {cases:6d} run  {outcome['crash']:4d} crashes  "
            f"({outcome['typed error']} typed errors, {outcome['accepted']} accepted)"
        )


# -------------------------------------------------------------------- load
class PeakRSS(threading.Thread):
    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.proc, self.peak, self.stop_event = psutil.Process(), 0, threading.Event()

    def run(self) -> None:
        while not self.stop_event.wait(0.01):
            self.peak = max(self.peak, self.proc.memory_info().rss)

    def stop(self) -> int:
        self.stop_event.set()
        self.join()
        return max(self.peak, self.proc.memory_info().rss)


def long_run(url: str, samples: int, work: Path, label: str, blocks: bool = True) -> None:
    u = np.where((np.arange(samples) // 500) % 2 == 0, 1.0, -1.0)
    path = work / f"long-{''.join(c if c.isalnum() else '-' for c in label)}.csv"
    with open_drive(url) as drive:
        if not blocks:
            drive.supports_block = False
        base = psutil.Process().memory_info().rss
        watch = PeakRSS()
        watch.start()
        t0 = time.perf_counter()
        result = stream_runs(drive, [(1, u)], 1000.0, path)
        seconds = time.perf_counter() - t0
        growth = watch.stop() - base
    size = path.stat().st_size
    print(
        f"  {label:22s} {result.samples:9d} samples  {seconds:7.1f} s  "
        f"{seconds / samples * 1e6:6.1f} us/sample  peak RSS +{growth / 1e6:5.2f} MB  "
        f"log {size / 1e6:5.1f} MB"
    )


def load(served_samples: int, work: Path) -> None:
    print("\nLong runs (the log streamed to disk; host-process peak RSS growth while streaming)")
    long_run(SIM_URL + "&pace=fast", 1_000_000, work, "sim:// (blocks)")
    long_run(SIM_URL + "&pace=fast", 1_000_000, work, "sim:// (per sample)", blocks=False)
    if served_samples:
        with ServedSim("canopen", SIM_URL) as served:
            long_run(served.url + HOST_KEYS, served_samples, work, "served CANopen")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--served-samples", type=int, default=1_000_000, metavar="N")
    p.add_argument("--fuzz", type=int, default=2000, metavar="N", help="cases per parser")
    p.add_argument("--skip-faults", action="store_true")
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        if not args.skip_faults:
            faults(work)
        if args.fuzz:
            fuzz(args.fuzz)
        load(args.served_samples, work)


if __name__ == "__main__":
    main()
