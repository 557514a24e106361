"""A fault seen through the real command line: ``servobench run`` against ``serve-sim --fault``."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from servobench.bench.logio import read_log
from servobench.bench.testing.fault_scenarios import SIM_URL, read_state
from servobench.bench.testing.served import ServedSim


@pytest.mark.parametrize(
    ("transport", "spec", "message"),
    [
        ("canopen", "drop@300", "no TPDO from node 2 within 100 ms of SYNC"),
        ("modbus-tcp", "exception@300:4", "Modbus exception 4 (server device failure)"),
    ],
)
def test_servobench_run_ends_with_one_line(
    transport: str, spec: str, message: str, tmp_path: Path
) -> None:
    state, log = tmp_path / "state.json", tmp_path / "log.csv"
    args = ["--fault", spec, "--state-file", str(state)]
    with ServedSim(transport, SIM_URL, args, clock="lockstep") as served:
        proc = subprocess.run(
            [sys.executable, "-m", "servobench", "run", "--drive", served.url + "&pace=fast",
             "--out", str(log), "--periods", "2", "--period", "0.5", "--amplitude", "1"],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    last = proc.stderr.splitlines()[-1]  # above it: the progress bar
    assert last.startswith("servobench: error: ") and message in last
    parsed = read_log(log)
    assert not parsed.complete and parsed.metadata["reason"] in last
    assert len(parsed.runs[0]) == 299  # every sample before cycle 300
    final = read_state(state)
    assert final["state"] == "disabled" and final["torque_off"] and final["command"] == 0.0
