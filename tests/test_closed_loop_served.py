"""Issue 11 over real protocols: ``servobench sidbe`` in closed loop against a served simulated drive.

Modbus TCP has no drive-side position loop: the host's hold loop keeps the
axis inside ``xmin``/``xmax`` through the register map, cycle by cycle.
CANopen has one: the served CiA 402 drive runs its own position loop in
cyclic synchronous position (0x6060 = 8) holding 0x607A, the excitation goes
out as the torque offset 0x60B2, and ``u`` is the torque the drive reports
applied (0x6077); the host measures the drive's gains from a trial under its
hold, checked here against the served drive's default gains as its source
defines them. Each drive is a ``serve-sim`` child process. A short
excitation (3 periods of 2 s) keeps the tests lean; the accuracy is that of
the in-process tests.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from servobench.bench.logio import read_log
from servobench.bench.testing.served import ServedSim

pytestmark = pytest.mark.slow  # closed-loop sidbe over served drives, 20 s

PLANT = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4&noise=0.01&seed=2"
SHORT = ["--period", "2", "--periods", "3", "--no-plots"]


def closed_sidbe(transport: str, timeouts: str, run: Path) -> dict:
    """``sidbe --json`` on a served drive with the travel window ±0.05; the model, checked against the plant."""
    with ServedSim(transport, PLANT, clock="lockstep") as served:
        # generous reply timeouts and watchdog: the served drive shares a busy test machine
        url = served.url + f"&pace=fast&{timeouts}&watchdog=2&xmin=-0.05&xmax=0.05"
        out = subprocess.run(
            [sys.executable, "-m", "servobench", "sidbe", "--drive", url, "--json", "--out", str(run), *SHORT],
            capture_output=True, text=True, timeout=300,
        )  # fmt: skip
    assert served.returncode == 0, served.stderr
    assert out.returncode == 0, out.stderr
    model = json.loads(out.stdout)
    assert model["pole"] == pytest.approx(-10.0, rel=0.01)
    assert model["dc_gain"] == pytest.approx(1.0, rel=0.01)
    assert model["coulomb_pos"] == pytest.approx(0.5, rel=0.05)
    assert model["coulomb_neg"] == pytest.approx(0.4, rel=0.05)
    assert model["loop"] == "closed"
    return model


def test_sidbe_holds_a_modbus_tcp_axis_inside_its_window(tmp_path):
    model = closed_sidbe("modbus-tcp", "timeout=2", tmp_path / "run")
    assert model["hold"]["where"] == "host"
    log = read_log(tmp_path / "run" / "log.csv")
    assert log.metadata["loop"] == "closed" and log.metadata["drive"].startswith("modbus+tcp://")
    for r in log.runs:
        assert -0.05 < r.x.min() and r.x.max() < 0.05  # noqa: SIM300
        assert r.u_exc is not None and r.x_ref is not None
    for name in ("probe.csv", "log-1.csv"):
        assert read_log(tmp_path / "run" / name).complete


def test_sidbe_with_the_drives_own_csp_loop(tmp_path):
    model = closed_sidbe("canopen", "pdo_timeout=1", tmp_path / "run")
    hold = model["hold"]
    assert hold["where"] == "drive" and "gains fitted" in hold["drive_loop"]
    # the served drive's default loop: 2 Hz, damping 0.7, integral at a fifth (its own source)
    w = 2 * np.pi * 2.0
    assert (hold["kp"], hold["ki"], hold["kd"]) == pytest.approx(
        (0.1 * w * w, 0.1 * w**3 * 0.2, 2 * 0.7 * w * 0.1 - 1.0), rel=0.02
    )
    log = read_log(tmp_path / "run" / "log.csv")
    assert log.metadata["loop"] == "closed" and log.metadata["hold"] == "drive"
    for r in log.runs:
        assert -0.05 < r.x.min() and r.x.max() < 0.05  # noqa: SIM300
        assert np.sqrt(np.mean((r.u - r.u_exc) ** 2)) > 0.05  # u is 0x6077: the drive's loop in it
