"""A default ``sidbe`` through every served transport in real time, under CPU load (issue 22).

The served drive runs in its own process with ``serve-sim --clock real``
(its axis moves in wall-clock time) at real-time priority (``--rt-priority``:
a real drive has a processor of its own), with and without its time stamp, while
two busy processes (one per core) load the machine from the host's start to the
end of its streaming. Each run streams a few
seconds (two periods of 0.5 s per run) at the rate the link carries; the
model must come out within 3 % of the plant (or its timing figure say it is not
within accuracy, with the error inside two of its prediction), and the log and the JSON must
carry ``clock_source`` and the timing figures.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from servobench.bench.log.io import read_log
from servobench.bench.testing.served import PATIENT_KEYS, ServedSim

#: one real-time bench at a time over the workers (conftest.realtime_bench)
pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("realtime_bench")]

PLANT = {"M": 0.01, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}
SIM = "sim://?M=0.01&B=1&fc_pos=0.5&fc_neg=0.4"
#: (transport, served with its time stamp); the ODrive protocol carries none.
CASES = [
    ("modbus-tcp", True), ("modbus-tcp", False), ("canopen", True), ("canopen", False),
    ("modbus-rtu", True), ("modbus-rtu", False), ("serial", False),
]  # fmt: skip
SHORT = ["--periods", "2", "--period", "0.5", "--no-plots", "--max-iterations", "1"]
#: How often the load looks for the end of the streaming [s].
STREAMED_POLL_S = 0.02


@contextmanager
def two_busy_processes(until: Path) -> Iterator[None]:
    """One spinning process per core (at most two), killed once the log ``until`` carries its
    trailer's status line (the streaming over: what follows is identification, which no clock
    judges), and whatever happens."""
    procs: list[subprocess.Popen] = []
    over = threading.Event()

    def streamed() -> bool:
        try:
            with open(until, "rb") as f:
                f.seek(max(0, f.seek(0, os.SEEK_END) - 256))
                tail = f.read()
        except OSError:
            return False
        at = tail.rfind(b"\n# status = ")  # the header's says running, the trailer's how it ended
        return at >= 0 and not tail[at:].startswith(b"\n# status = running")

    def watch() -> None:
        while not over.wait(STREAMED_POLL_S):
            if streamed():
                break
        for p in procs:
            p.kill()

    watcher = threading.Thread(target=watch, daemon=True)
    try:
        for cpu in sorted(os.sched_getaffinity(0))[:2]:
            procs.append(subprocess.Popen(
                [sys.executable, "-c", f"import os\nos.sched_setaffinity(0, {{{cpu}}})\nwhile True: pass"]
            ))  # fmt: skip
        watcher.start()
        yield
    finally:
        over.set()
        if watcher.is_alive():
            watcher.join()
        for p in procs:
            p.kill()
        for p in procs:
            p.wait()


@pytest.mark.parametrize(("transport", "stamped"), CASES, ids=[f"{t}-{'stamp' if s else 'nostamp'}" for t, s in CASES])
def test_default_sidbe_in_real_time_under_load(transport, stamped, tmp_path):
    # the drive has its own processor, as a real one: real-time priority in its process
    args = ["--clock", "real", "--rt-priority", "70"]
    args += [] if stamped or transport == "serial" else ["--no-timestamp"]
    # the drive is up before the load starts (as a bench's drive is before its run): the load
    # covers the host's start-up and its streaming, up to the log's trailer (the identification
    # after it is judged by no clock: under the load it took 80 % of these tests' spinning CPU)
    with ServedSim(transport, SIM, args) as served, two_busy_processes(tmp_path / "run" / "log-1.csv"):
        proc = subprocess.run(
            [sys.executable, "-m", "servobench", "sidbe", "--drive", served.url + PATIENT_KEYS[transport], "--json",
             "--out", str(tmp_path / "run"), *SHORT],
            capture_output=True, text=True, timeout=300,
        )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    model = json.loads(proc.stdout)
    timing = model["timing"]
    worst = max(abs(model[key] / true - 1.0) * 100.0 for key, true in PLANT.items())
    # a run the loaded host put beyond 3 % must say so: its timing figure not within accuracy
    # and its error within the figure's bound (two of its 1-sigma prediction) (a fresh-clone suite gave
    # ODrive serial B 4.05 % off, fit 95.9 %, with 3.95 % predicted and "not within accuracy")
    told = not timing["within_accuracy"] and timing["model_error_bound_pct"] >= worst
    # and so does its verdict: over the fit threshold, a plain pass only within accuracy
    assert model["verdict"] == ("pass" if timing["within_accuracy"] else "pass with remarks"), timing
    assert worst <= 3.0 or told, (worst, {k: model[k] for k in PLANT}, timing)
    source = "drive" if stamped else "host"
    assert model["clock_source"] == source
    for key in ("jitter_p50_s", "jitter_p99_s", "jitter_max_s", "missed_cycles",
                "model_error_pct", "model_error_max_pct", "within_accuracy"):  # fmt: skip
        assert key in timing
    assert timing["jitter_p99_s"] is not None and timing["jitter_p99_s"] >= 0
    log = read_log(tmp_path / "run" / "log.csv")
    assert log.complete
    assert log.metadata["clock_source"] == source
    assert log.metadata["rt_gc"] == "frozen/disabled"
    for key in ("host_jitter_p50_s", "host_jitter_p99_s", "host_jitter_max_s", "missed_cycles"):
        assert key in log.metadata
    t_unc = log.runs[0].extra["t_unc"]
    assert (t_unc == 0).all() if stamped else (t_unc > 0).all()
