"""Achieved closed-loop cycle rate and jitter per transport, beside the physical limit of the link.

Each transport serves the simulated drive in its own process (``servobench
serve-sim``) and the host streams a square wave through the real protocol
stack as fast as the link answers (``pace=fast``); then at a fixed 1 kHz or
80 % of the link limit (``pace=real``, the runner's deadline schedule) to show
the jitter a bench would see. Link limits:

- CANopen at 1 Mbit/s: SYNC + RPDO + TPDOs, with and without worst-case bit
  stuffing (on the generic served drive servobench maps a 6-byte RPDO:
  controlword, target torque, torque offset; and two 8-byte TPDOs; a
  drive-side hold adds a 4-byte RPDO, which ``Drive.max_rate_hz`` counts);
- Modbus RTU, Modbus TCP and serial: the drive's own ``Drive.max_rate_hz()``
  (the frames or lines of one cycle on the wire, from
  :mod:`servobench.drivers.link_budget`, plus the map's turnaround per
  Modbus transaction and the serial driver's fault poll); beside it the
  bytes actually exchanged on the serial line.

The paced row streams at the rate ``sidbe`` would choose by default
(:func:`servobench.drivers.link_budget.default_rate_hz`).

Run: ``python benchmarks/transport_rate.py [--n 3000]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from servobench.bench.testing.served import ServedSim
from servobench.clock import sleep_until
from servobench.drivers.link_budget import (
    canopen_cycle_s,
    default_rate_hz,
    modbus_rtu_cycle_s,
    modbus_rtu_frames,
    modbus_tcp_cycle_s,
    uart_cycle_s,
)
from servobench.drivers.registry import open_drive

PLANT = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"


def measure(url: str, n: int, rate_hz: float | None) -> tuple[np.ndarray, object]:
    """Host-side periods [s] of ``n`` exchanges, free-running or paced at ``rate_hz``."""
    u = np.where((np.arange(n) // 100) % 2 == 0, 0.8, -0.8)
    with open_drive(url) as drive:
        drive.set_cycle(1e-3)
        drive.enable()
        for _ in range(20):
            drive.exchange(0.0)
        counters = (getattr(drive, "bytes_sent", 0), getattr(drive, "bytes_received", 0))
        t = np.empty(n + 1)
        t[0] = time.monotonic()
        for k in range(n):
            if rate_hz:
                sleep_until(t[0] + (k + 1) / rate_hz)
            drive.exchange(u[k])
            t[k + 1] = time.monotonic()
        moved = getattr(drive, "bytes_sent", 0) + getattr(drive, "bytes_received", 0) - sum(counters)
        regmap = getattr(drive, "regmap", None)
    return np.diff(t), (moved / n, regmap)


def link_limit(transport: str, url: str, extra: tuple[float, object]) -> tuple[float, str]:
    bytes_per_cycle, regmap = extra
    if transport == "canopen":
        best, worst = canopen_cycle_s([6, 0, 8, 8])
        return worst, f"RPDO(6)+SYNC+2 TPDO(8): {best * 1e6:.0f}-{worst * 1e6:.0f} us"
    limit_s = 1.0 / open_drive(url).max_rate_hz()
    if transport == "modbus-rtu":
        frames = modbus_rtu_frames(regmap["command"].count, regmap.feedback.count, regmap.fc23)
        wire_s = modbus_rtu_cycle_s(frames)
        return limit_s, (
            f"{'FC23' if regmap.fc23 else 'write+read'} {frames} B + t3.5 = {wire_s * 1e3:.2f} ms, "
            f"+ turnaround {regmap.turnaround_s * 1e3:g} ms per transaction"
        )
    if transport == "modbus-tcp":
        w, r = regmap["command"].count, regmap.feedback.count
        adus = [7 + 10 + 2 * w, 7 + 2 + 2 * r]  # MBAP + FC23 request / response PDU
        wire_us = modbus_tcp_cycle_s(adus) * 1e6
        return limit_s, (
            f"FC23 on 100 Mbit/s Ethernet ({wire_us:.0f} us) + turnaround "
            f"{regmap.turnaround_s * 1e3:g} ms"
        )
    return limit_s, (
        f"Drive.max_rate_hz(), fault poll included; measured {bytes_per_cycle:.1f} B/cycle = "
        f"{1 / uart_cycle_s(bytes_per_cycle):.0f}/s at 115200 baud"
    )


def stats(period_s: np.ndarray) -> str:
    return (
        f"{1 / period_s.mean():8.0f} /s  jitter std {period_s.std() * 1e6:6.0f} us  "
        f"p99 {np.percentile(period_s, 99) * 1e3:6.2f} ms  max {period_s.max() * 1e3:6.2f} ms"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=3000, help="exchanges per measurement")
    parser.add_argument(
        "--transports", default="canopen,modbus-tcp,modbus-rtu,serial", help="comma-separated"
    )
    args = parser.parse_args()
    print(f"{args.n} exchanges per row; served simulated drive in a child process\n")
    for transport in args.transports.split(","):
        n = args.n if transport in ("canopen", "modbus-tcp") else max(300, args.n // 5)
        with ServedSim(transport, PLANT) as served:
            url = served.url + "&pace=fast"
            free, extra = measure(url, n, None)
            limit_s, how = link_limit(transport, url, extra)
            paced_hz = default_rate_hz(1 / limit_s, 1000.0)
            paced, _ = measure(url, n, paced_hz)
        achieved = 1 / free.mean()
        print(f"{transport:11s} free-running {stats(free)}")
        print(f"{'':11s} paced {paced_hz:5.0f} Hz {stats(paced)}")
        note = "  (the socketcand hub has no bit timing)" if transport == "canopen" else ""
        print(
            f"{'':11s} link limit {1 / limit_s:8.0f} /s ({how}); achieved/limit = "
            f"{100 * achieved * limit_s:.1f} %{note}\n"
        )


if __name__ == "__main__":
    main()
