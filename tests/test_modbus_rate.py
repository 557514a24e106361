"""The served Modbus RTU link is never faster than the wire (rates are figures: benchmarks/transport_rate.py).

The served RTU link emulates the line (:mod:`servobench.sim_backend.servers.pty_link`): 10 bits
per byte at the baud rate and the Modbus t3.5 silence (1.75 ms above 19200
baud) that ends every frame, so one cycle cannot beat the sum of its frames'
line times. Run with ``-s`` to see the figures.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from servobench.bench.testing.served import PATIENT_KEYS, ServedSim
from servobench.drivers.link_budget import modbus_rtu_cycle_s, modbus_rtu_frames
from servobench.drivers.modbus.regmap import RegisterMap, load_map, resolve_map
from servobench.drivers.registry import open_drive

BAUD = 115200


def rtu_cycle_limit_s(regmap: RegisterMap, fc23: bool, baud: int = BAUD) -> float:
    """Line time of one cycle [s]: the RTU frames (address + PDU + CRC) and a t3.5 after each."""
    frames = modbus_rtu_frames(regmap["command"].count, regmap.feedback.count, fc23)
    return modbus_rtu_cycle_s(frames, baud)


def measure(url: str, n: int) -> np.ndarray:
    """Periods of ``n`` square-wave exchanges [s]."""
    u = np.where((np.arange(n) // 100) % 2 == 0, 0.8, -0.8)
    with open_drive(url) as drive:
        drive.set_cycle(0.001)
        drive.enable()
        for _ in range(10):
            drive.exchange(0.0)
        t = np.empty(n + 1)
        t[0] = time.perf_counter()
        for k in range(n):
            drive.exchange(u[k])
            t[k + 1] = time.perf_counter()
    return np.diff(t)


def report(label: str, period_s: np.ndarray, limit_s: float | None = None) -> float:
    rate_hz = 1.0 / period_s.mean()
    extra = ""
    if limit_s is not None:
        extra = f", link limit {1 / limit_s:.1f}/s ({limit_s * 1e3:.2f} ms) -> {100 * rate_hz * limit_s:.1f} %"
    print(
        f"\n{label}: {rate_hz:.1f} exchanges/s{extra}; period mean {period_s.mean() * 1e3:.3f} ms, "
        f"std {period_s.std() * 1e6:.0f} us, p99 {np.percentile(period_s, 99) * 1e3:.3f} ms, "
        f"max {period_s.max() * 1e3:.3f} ms"
    )
    return rate_hz


@pytest.mark.slow
@pytest.mark.parametrize(("fc23", "n"), [(True, 150), (False, 80)])
def test_rtu_exchange_rate_near_the_link_limit(tmp_path, fc23, n):
    regmap = load_map("servobench-sim")
    limit_s = rtu_cycle_limit_s(regmap, fc23)
    with ServedSim("modbus-rtu") as served:
        url = served.url + PATIENT_KEYS["modbus-rtu"]  # the drive answers, late under load
        if not fc23:  # the same served drive, a client map without FC23: write, then read
            path = tmp_path / "no-fc23.toml"
            path.write_text(
                Path(resolve_map("servobench-sim"))
                .read_text()
                .replace("fc23 = true", "fc23 = false")
            )
            url = url.replace("map=servobench-sim", f"map={path}")
        period_s = measure(url, n)
    rate_hz = report(
        f"modbus+rtu {BAUD} baud {'FC23' if fc23 else 'write-then-read'}", period_s, limit_s
    )
    assert rate_hz <= 1.01 / limit_s  # the line emulation holds: no faster than the wire
    # How close to the limit it gets is a figure, not a test: benchmarks/transport_rate.py.
