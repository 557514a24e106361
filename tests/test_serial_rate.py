"""The served serial link is never faster than the wire (rates are figures: benchmarks/transport_rate.py).

The served simulator emulates UART byte time (a pty has none), so the rate
cannot beat ``baud / (10 * bytes per exchange)``; the driver should get
close to it. Run with ``-s`` to see the figures.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from servobench.bench.testing.served import PATIENT_KEYS, ServedSim
from servobench.drivers.registry import open_drive

N_EXCHANGES = 300
BAUD = 115200


@pytest.mark.slow
@pytest.mark.parametrize("extra", ["", "&checksum=1"])
def test_exchange_rate_near_the_link_limit(extra):
    sim = ServedSim("serial", "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4")
    sim.start()
    try:
        # patient: a loaded machine may hold the served drive past the 0.1 s default reply time
        with open_drive(sim.url + PATIENT_KEYS["serial"] + extra) as drive:
            drive.set_cycle(0.001)
            drive.enable()
            for _ in range(20):
                drive.exchange(0.0)
            u = np.where((np.arange(N_EXCHANGES) // 100) % 2 == 0, 0.8, -0.8)
            bytes0 = drive.bytes_sent + drive.bytes_received
            t = np.empty(N_EXCHANGES + 1)
            t[0] = time.monotonic()
            for k in range(N_EXCHANGES):
                drive.exchange(u[k])
                t[k + 1] = time.monotonic()
            n_bytes = drive.bytes_sent + drive.bytes_received - bytes0
    finally:
        assert sim.stop() == 0
    elapsed_s = t[-1] - t[0]
    period_s = np.diff(t)
    bytes_per_exchange = n_bytes / N_EXCHANGES
    link_s = n_bytes * 10 / BAUD  # 8N1 on the wire, request and reply in turn
    rate_hz = N_EXCHANGES / elapsed_s
    limit_hz = N_EXCHANGES / link_s
    print(
        f"\nserial{extra or ' (no checksum)'}: {rate_hz:.1f} exchanges/s, "
        f"{bytes_per_exchange:.2f} bytes/exchange, link limit {limit_hz:.1f}/s "
        f"-> {100 * rate_hz / limit_hz:.1f} %; period mean {period_s.mean() * 1e3:.3f} ms, "
        f"std {period_s.std() * 1e6:.0f} us, p99 {np.percentile(period_s, 99) * 1e3:.3f} ms, "
        f"max {period_s.max() * 1e3:.3f} ms"
    )
    assert 28 <= bytes_per_exchange <= 48  # "c 0 -0.8\nf 0\n" + "x.xxxxxx v.vvvvvv\r\n" (+ polls)
    assert rate_hz <= limit_hz * 1.01  # the byte-time emulation holds: no faster than the wire
    # How close to the limit it gets is a figure, not a test: benchmarks/transport_rate.py.
