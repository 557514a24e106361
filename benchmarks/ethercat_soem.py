"""EtherCAT over a private veth link: SOEM at 1 kHz for 10 s, and servobench's ``ethercat://`` drive.

Each part runs in a child process inside its own user and network namespace
(:mod:`servobench.bench.testing.ethercat_link`), with ``servobench serve-sim
--transport ethercat`` on the other end of a veth pair:

- SOEM (pysoem, no servobench driver) on a lock-step slave: scan time, then CST at 1 kHz for
  ``--seconds`` (10 s, the issue's run) with a torque square wave, paced to
  absolute deadlines; the round trip of each frame (send to receive), the
  host period, frames with a wrong working counter, and the largest velocity
  error against the plant simulated offline with the same commands;
- servobench's ``ethercat://`` drive: exchanges per second unpaced, and the
  round trip percentiles;
- the drive paced at 1 kHz on a real-time slave (``--clock real``): the
  spacing of its samples on the DC clock (0x10F8), and the largest velocity
  error of the plant integrated from each sample to the next over the DC
  instants, against over a nominal 1 ms grid (what a cycle-counting clock
  would assume).

Run: ``python benchmarks/ethercat_soem.py [--seconds 10]``.

Measured on the shared 2-core machine while four other sessions ran their tests::

    SOEM (pysoem) against the served slave, 10000 cycles at 1 kHz:
      scan: 1 slave in 8.6 ms
      round trip: p50 195 us, p90 554 us, p99 3078 us, p99.9 7719 us, max 68466 us
      host period: p1 201 us, p50 965 us, p99 5716 us; 1202 periods > 1.5 ms
      frames with a wrong working counter: 0
      largest velocity error against the plant: 5.00e-07 rad/s
    servobench ethercat:// drive, unpaced:
      2639 exchanges/s; round trip p50 163 us, p90 314 us, p99 4710 us; frames sent again: 0

and, with the real-time DC-synchronous slave (``--seconds 5``, load average 11 on 2 cores;
the unpaced drive then makes one exchange per SYNC0 event)::

    servobench ethercat:// drive, unpaced:
      950 exchanges/s; round trip p50 997 us, p90 1098 us, p99 2777 us; frames sent again: 0
    ethercat:// paced at 1 kHz on a real-time slave (--clock real), 5000 cycles:
      drive clock: 0x10F8 DC system time of each sample [ns]
      sample spacing on the DC clock: p1 1000 us, p50 1000 us, p99 4000 us, max 8000 us
      largest one-step velocity error of the plant from each sample: 9.85e-07 rad/s on the DC
      instants, 5.67e-02 rad/s on a nominal 1 ms grid
"""

from __future__ import annotations

import argparse
import os
import struct
import time

import numpy as np

from servobench.bench.testing.ethercat_link import link_unavailable, run_on_link

PLANT = "sim://?M=0.1&B=1&fc_pos=0.2&fc_neg=0.15"
SECONDS = 10.0
SECONDS_ENV = "SERVOBENCH_ETHERCAT_BENCH_SECONDS"


def soem_run(iface: str, url: str) -> dict:
    import pysoem

    pysoem.settings.timeouts.ret = 20_000
    pysoem.settings.timeouts.safe = 200_000
    seconds = float(os.environ.get(SECONDS_ENV, SECONDS))
    master = pysoem.Master()
    master.open(iface)
    t0 = time.perf_counter()
    found = master.config_init()
    scan_s = time.perf_counter() - t0
    slave = master.slaves[0]
    slave.sdo_write(0x6060, 0, struct.pack("<b", 10))
    master.config_map()
    master.send_processdata()
    master.receive_processdata(500_000)
    master.state = pysoem.OP_STATE
    master.write_state()
    while master.state_check(pysoem.OP_STATE, 2000) != pysoem.OP_STATE:
        master.send_processdata()
        master.receive_processdata(500_000)
    for cw in (0x06, 0x07, 0x0F):
        for _ in range(5):
            slave.output = struct.pack("<Hh4xh", cw, 0, 0)
            master.send_processdata()
            master.receive_processdata(500_000)
    n = int(seconds * 1000)
    u = np.where((np.arange(n) // 500) % 2 == 0, 600, -600)
    rtt, period, v, bad = np.empty(n), np.empty(n), np.empty(n), 0
    deadline = last = time.perf_counter()
    for k in range(n):
        deadline += 1e-3
        slave.output = struct.pack("<Hh4xh", 0x0F, int(u[k]), 0)
        t = time.perf_counter()
        master.send_processdata()
        wkc = master.receive_processdata(500_000)
        rtt[k] = time.perf_counter() - t
        period[k], last = t - last, t
        bad += wkc != master.expected_wkc
        v[k] = struct.unpack_from("<Hii", slave.input)[2] * 1e-6
        time.sleep(max(0.0, deadline - time.perf_counter()))
    master.state = pysoem.INIT_STATE
    master.write_state()
    master.close()
    from servobench.sim_backend.physics.plant import PlantParams, simulate

    v_ref, _ = simulate(u / 1000.0, 1000.0, PlantParams(M=0.1, B=1.0, coulomb_pos=0.2,
                                                        coulomb_neg=0.15))  # fmt: skip
    return {
        "found": found, "scan_ms": scan_s * 1e3, "n": n, "bad_wkc": int(bad),
        "rtt_us": np.percentile(rtt * 1e6, [50, 90, 99, 99.9]).tolist(), "rtt_max_us": rtt.max() * 1e6,
        "period_us": np.percentile(period[1:] * 1e6, [1, 50, 99]).tolist(),
        "late_periods": int(np.sum(period[1:] > 1.5e-3)),
        "v_err_max": float(np.max(np.abs(v - v_ref))),
    }  # fmt: skip


def drive_run(iface: str, url: str) -> dict:
    from servobench.drivers.registry import open_drive

    n = 3000
    with open_drive(url + "&pace=fast") as drive:
        drive.set_cycle(0.001)
        drive.enable()
        rtt = np.empty(n)
        t0 = time.perf_counter()
        for k in range(n):
            t = time.perf_counter()
            drive.exchange(0.6 if (k // 500) % 2 == 0 else -0.6)
            rtt[k] = time.perf_counter() - t
        rate = n / (time.perf_counter() - t0)
        drive.disable()
        errors = dict(drive.link_recoveries())
    return {"rate_hz": rate, "rtt_us": np.percentile(rtt * 1e6, [50, 90, 99]).tolist(), **errors}


def realtime_run(iface: str, url: str) -> dict:
    """The ``ethercat://`` drive paced at 1 kHz on a real-time slave, 0x10F8 its drive clock."""
    from servobench.drivers.registry import open_drive
    from servobench.sim_backend.physics.plant import Plant, PlantParams

    n = int(float(os.environ.get(SECONDS_ENV, SECONDS)) * 1000)
    u = np.where((np.arange(n) // 500) % 2 == 0, 0.6, -0.6)
    with open_drive(url + "&watchdog=1") as drive:
        drive.set_cycle(0.001)
        drive.enable()
        rows, start = [], time.monotonic()
        for k in range(n):
            time.sleep(max(0.0, start + k * 1e-3 - time.monotonic()))
            fb = drive.exchange(float(u[k]))[0]
            rows.append((fb.t_s, fb.velocity, fb.position))
        clock = drive.log_metadata()["drive_clock"]
    t, v, x = np.array(rows).T
    dt = np.diff(t)
    plant = Plant(PlantParams(M=0.1, B=1.0, coulomb_pos=0.2, coulomb_neg=0.15))

    def one_step_error(spans: np.ndarray) -> float:  # the plant from each sample to the next
        worst = 0.0
        for k, span in enumerate(spans):
            plant.reset(v[k], x[k])
            plant.hold(u[k], span)
            worst = max(worst, abs(plant.state.v - v[k + 1]))
        return worst

    return {
        "n": n, "clock": clock, "dt_us": np.percentile(dt * 1e6, [1, 50, 99, 100]).tolist(),
        "err_dc": one_step_error(dt), "err_nominal": one_step_error(np.full_like(dt, 1e-3)),
    }  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=SECONDS)
    args = p.parse_args()
    why = link_unavailable()
    if why is not None:
        raise SystemExit(f"no private EtherCAT link here: {why}")
    os.environ[SECONDS_ENV] = str(args.seconds)  # the child process inherits it
    # lock-step: the velocity error against the offline plant is then the codec's alone
    soem = run_on_link(__file__, "soem_run", PLANT, ["--clock", "lockstep"],
                       timeout_s=120 + 2 * args.seconds)  # fmt: skip
    print(f"SOEM (pysoem) against the served slave, {soem['n']} cycles at 1 kHz:")
    print(f"  scan: {soem['found']} slave in {soem['scan_ms']:.1f} ms")
    p50, p90, p99, p999 = soem["rtt_us"]
    print(f"  round trip: p50 {p50:.0f} us, p90 {p90:.0f} us, p99 {p99:.0f} us, "
          f"p99.9 {p999:.0f} us, max {soem['rtt_max_us']:.0f} us")  # fmt: skip
    lo, mid, hi = soem["period_us"]
    print(f"  host period: p1 {lo:.0f} us, p50 {mid:.0f} us, p99 {hi:.0f} us; "
          f"{soem['late_periods']} periods > 1.5 ms")  # fmt: skip
    print(f"  frames with a wrong working counter: {soem['bad_wkc']}")
    print(f"  largest velocity error against the plant: {soem['v_err_max']:.2e} rad/s")
    drive = run_on_link(__file__, "drive_run", PLANT)
    print("servobench ethercat:// drive, unpaced:")
    print(f"  {drive['rate_hz']:.0f} exchanges/s; round trip p50 {drive['rtt_us'][0]:.0f} us, "
          f"p90 {drive['rtt_us'][1]:.0f} us, p99 {drive['rtt_us'][2]:.0f} us; "
          f"frames sent again: {drive.get('wkc_errors', 0)}")  # fmt: skip
    real = run_on_link(__file__, "realtime_run", PLANT, ["--clock", "real"],
                       timeout_s=120 + 2 * args.seconds)  # fmt: skip
    print(f"ethercat:// paced at 1 kHz on a real-time slave (--clock real), {real['n']} cycles:")
    print(f"  drive clock: {real['clock']}")
    lo, mid, hi, top = real["dt_us"]
    print(f"  sample spacing on the DC clock: p1 {lo:.0f} us, p50 {mid:.0f} us, p99 {hi:.0f} us, "
          f"max {top:.0f} us")  # fmt: skip
    print(f"  largest one-step velocity error of the plant from each sample: "
          f"{real['err_dc']:.2e} rad/s on the DC instants, "
          f"{real['err_nominal']:.2e} rad/s on a nominal 1 ms grid")  # fmt: skip


if __name__ == "__main__":
    main()
