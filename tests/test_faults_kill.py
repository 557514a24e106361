"""The host process dies mid-run: the drive's watchdog stops the axis, the log survives.

A host process streams to a served drive (``watchdog=0.2``) and is killed
with SIGKILL mid-run: no clean-up runs on the host, so the drive must stop
by itself (watchdog fault 0x8130, by its state report) and the log, written
off the cyclic path by a writer thread every ``FLUSH_S`` (5 ms), must hold
every row streamed but those of the last flush period or two, each equal to the plant's lock-step
simulation, and read as incomplete (its header's ``status = running`` is
never overwritten). With SIGTERM the runner itself stops and disables the
axis and marks the log ``incomplete`` with the reason.
"""

from __future__ import annotations

import math
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from servobench.bench.log.io import read_log
from servobench.bench.run.ring_writer import FLUSH_S
from servobench.bench.testing.fault_scenarios import (
    FS_HZ,
    HOST_KEYS,
    SERVE_ARGS,
    SIM_URL,
    excitation,
    read_state,
    wait_for_state,
)
from servobench.bench.testing.served import ServedSim
from servobench.sim_backend.device import WATCHDOG_FAULT
from servobench.sim_backend.physics.plant import PlantParams, simulate

PARAMS = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)
#: Samples the host announces before it is killed.
STREAMING_AFTER = 60
#: Rows a SIGKILL may take with it: those the writer thread had not flushed yet (two periods).
UNFLUSHED = math.ceil(2 * FLUSH_S * FS_HZ)
#: The host: stream a long run at the real cycle rate, say when it is under way.
HOST = f"""
import sys
import numpy as np
from servobench.bench.run.runner import stream_runs
from servobench.drivers.registry import open_drive
from servobench.bench.testing.fault_scenarios import excitation

said = []
def progress(done, total):
    if done >= {STREAMING_AFTER} and not said:
        said.append(print("streaming", flush=True))

u = np.tile(excitation()[0][1], 60)
with open_drive(sys.argv[1]) as drive:
    stream_runs(drive, [(1, u)], {FS_HZ}, sys.argv[2], pace="real", progress=progress)
"""
#: Quantisation of the served feedback (1e-6 units per count, 6 decimals on serial).
ATOL = 1e-6


def run_host_and_kill(url: str, log: Path, state_path: Path, sig: signal.Signals) -> subprocess.Popen[str]:
    """Start the host, and kill it once it streams and the drive reports itself enabled.

    Waiting for the drive's own report of ``enabled`` first means the state read after
    the kill cannot be the report written before the host enabled the axis (its
    ``disabled`` is one of the states the test waits for).
    """
    host = subprocess.Popen(
        [sys.executable, "-c", HOST, url, str(log)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        line = host.stdout.readline()
        assert line.strip() == "streaming", host.stderr.read() if host.poll() is not None else line
        running = wait_for_state(state_path, ("enabled",))
        assert running.get("state") == "enabled", running
        host.send_signal(sig)
        host.wait(10)
    finally:
        if host.poll() is None:
            host.kill()
            host.wait()
        host.stdout.close()
    return host


@pytest.mark.parametrize(
    ("transport", "sig"),
    [
        ("canopen", signal.SIGKILL),
        ("modbus-tcp", signal.SIGKILL),
        ("modbus-rtu", signal.SIGKILL),
        ("serial", signal.SIGKILL),
        ("canopen", signal.SIGTERM),
    ],
    ids=lambda v: v.name if isinstance(v, signal.Signals) else v,
)
def test_killed_host(transport: str, sig: signal.Signals, tmp_path: Path) -> None:
    state_path, log_path = tmp_path / "state.json", tmp_path / "log.csv"
    args = [*SERVE_ARGS[transport], "--state-file", str(state_path)]
    with ServedSim(transport, SIM_URL, args, clock="lockstep") as served:
        host = run_host_and_kill(served.url + HOST_KEYS + "&watchdog=0.2", log_path, state_path, sig)
        state = wait_for_state(state_path, ("fault", "disabled"))
        stderr = host.stderr.read()
        host.stderr.close()
    assert host.returncode != 0
    assert "Traceback" not in stderr or sig is signal.SIGTERM, stderr
    log = read_log(log_path)
    run = log.runs[0]
    assert not log.complete and len(run) >= STREAMING_AFTER - UNFLUSHED
    u = np.tile(excitation()[0][1], 60)[: len(run)]
    v_ref, x_ref = simulate(u, FS_HZ, PARAMS)
    np.testing.assert_array_equal(run.u, u)
    np.testing.assert_allclose(run.v, v_ref, atol=ATOL)
    np.testing.assert_allclose(run.x, x_ref, atol=ATOL)
    if sig is signal.SIGKILL:  # nobody on the host stopped the axis: the watchdog did
        assert log.metadata["status"] == "running" and "reason" not in log.metadata
        assert state["state"] == "fault" and state["fault_code"] == WATCHDOG_FAULT
        assert state["watchdog_trips"] == 1
    else:  # the runner caught SIGTERM: stopped and disabled by the host
        assert log.metadata["status"] == "incomplete"
        assert log.metadata["reason"] == "terminated (SIGTERM)"
        assert state["state"] == "disabled" and state["watchdog_trips"] == 0
    assert state["torque_off"] and state["command"] == 0.0
    final = read_state(state_path)  # at serve-sim's exit: still no torque
    assert final["final"] and final["torque_off"]
