"""``servobench sidbe`` with default options through every served transport (issue 10 §4).

Each run chooses its cycle rate from the drive's link (Modbus RTU at 115200
baud: 100 Hz from its 137 cycles/s; serial at 115200 baud: 200 Hz from its
284; Modbus TCP and CANopen: the default 1 kHz), streams the default
excitation in real time (4 periods of 4 s, twice: 32 s), and must finish
within that nominal time, plus the link's set-up, and identify the plant
within 1 %. The two slow links (they keep the CPU mostly idle) run beside
Modbus TCP, and CANopen alone: a host holding a 1 kHz schedule keeps about
one core busy. Each group takes about 42 s: on the RTU link the default
excitation costs 32 s of streaming at 100 Hz, as at every rate (its length
is set in seconds), plus about 10 s of start-up, identification and plots.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from servobench.bench.excitation import DEFAULT_PERIOD_S, DEFAULT_PERIODS
from servobench.bench.logio import read_log
from servobench.bench.testing.served import ServedSim
from servobench.drivers.link_budget import default_rate_hz

PLANT = {"M": 0.1, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}
SIM = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"
#: Transports run side by side.
GROUPS = (("serial", "modbus-rtu", "modbus-tcp"), ("canopen",))
#: Nominal streaming time: two runs of the default excitation [s].
NOMINAL_S = 2 * DEFAULT_PERIODS * DEFAULT_PERIOD_S
#: Process start, imports, drive set-up, identification and plots, on a loaded 2-core machine [s].
SETUP_S = 30.0


def sidbe(transport: str, out: Path, results: dict) -> None:
    with ServedSim(transport, SIM, clock="lockstep") as served:  # regular drive clock, exact
        t0 = time.monotonic()
        proc = subprocess.run(
            [sys.executable, "-m", "servobench", "sidbe", "--drive", served.url, "--json",
             "--out", str(out)],
            capture_output=True, text=True, timeout=NOMINAL_S + 120,
        )  # fmt: skip
        results[transport] = (proc, time.monotonic() - t0)


@pytest.mark.slow
@pytest.mark.parametrize("group", GROUPS, ids=lambda g: "+".join(g))
def test_sidbe_with_default_options_fits_every_link(group, tmp_path):
    results: dict = {}
    threads = [threading.Thread(target=sidbe, args=(t, tmp_path / t, results)) for t in group]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for transport in group:
        proc, elapsed_s = results[transport]
        assert proc.returncode == 0, f"{transport}: {proc.stderr}"
        model = json.loads(proc.stdout)
        for key, true in PLANT.items():
            assert model[key] == pytest.approx(true, rel=0.01), (transport, key)
        log = read_log(tmp_path / transport / "log.csv")
        fs = float(log.metadata["fs"])
        assert model["fs"] == fs
        # the rate follows the link, whose limit every transport logs (CANopen: the bus's bitrate)
        assert fs == default_rate_hz(float(log.metadata["link_max_rate_hz"]), 1000.0)
        # the excitation follows the rate: a whole number of samples per period, lines below fs/20
        assert int(log.metadata["samples_per_period"]) == round(DEFAULT_PERIOD_S * fs)
        assert max(float(f) for f in log.metadata["freqs"].split(",")) <= fs / 20
        for run in log.runs:  # in real time, on schedule: no run overran its nominal length
            nominal_s = (len(run) - 1) / fs
            assert run.extra["t_host"][-1] <= 1.03 * nominal_s + 0.5, (transport, run.run)
            if transport != "serial":  # a drive clock, lock-step while streamed: regular
                assert np.allclose(np.diff(run.t), 1 / fs, rtol=0, atol=2e-6)
        achieved = float(log.metadata["fs_achieved"])
        assert achieved == pytest.approx(model["fs_achieved"]) and achieved > 0.95 * fs
        assert elapsed_s <= NOMINAL_S + 1.0 + SETUP_S, (transport, elapsed_s)
