"""Drive clock (issue 28): ``sidbe`` against served drives that run on a control tick of their own.

Every served drive runs in its own process, ``servobench serve-sim --transport T
--clock real --tick S`` (the physics integrates wall-clock time; the drive
samples at its ticks, from a random phase, and a command acts from its next
tick; a read returns the last tick's sample, and the time stamp, where the
protocol has one, is that tick's instant), at real-time priority
(``--rt-priority``, as ``benchmarks/realtime.py``), with ``--state-file``: the
drive's own record of its timing (``"tick"``: its tick, phase, the mean action
delay of its commands, the reads that repeated a tick, the ticks skipped).
The matrix: Modbus TCP, Modbus RTU and ODrive serial (no time stamp ever) at
ticks 0.125, 0.25, 0.5, 1 and 2 ms; CANopen and EtherCAT at a 1 ms tick; each
with its time stamp and without (``--no-timestamp``); on the machine as it is
("idle") and with two busy processes, one per core ("busy", the load generator
of ``benchmarks/realtime.py``); ``--loads stall`` adds a host stopped (SIGSTOP) for
30-150 ms every 0.5-1.5 s beside them, mid-exchange as the machine pleases (not
for EtherCAT, whose host runs inside its link's namespace). Plant: ``sim://?M=0.01&B=1&fc_pos=0.5&fc_neg=0.4&seed=N``
(pole -100), a new seed per run. The host runs ``servobench sidbe --drive URL
--json --no-plots`` at its defaults (``--quick``: 2 periods of 2 s per run, as
``realtime.py --quick``). EtherCAT runs on a private veth link in a network
namespace of its own (:mod:`servobench.bench.testing.ethercat_link`: its
namespace prefix, interfaces and carrier wait; the child that serves the slave
is this file's ``--ethercat-child``, as that module's child always gives the slave
real-time priority); where no such link can be made one line says why.

Printed per run: the errors of M, B and both Coulomb levels [%], the
verification fit [%], the identified action delay [ms] +- its 1 sigma beside
the drive record's mean delay over the commands that changed the value [ms]
(``mean_change_delay_s``: a repeated command acts alike from either tick, so
only a change shows its delay) and their difference, the repeated samples
and skipped ticks the timing figure found, the rows read a SYNC0 event late
(EtherCAT, ``late_samples``: their commands act from the log's ``t_act``), the predicted model error (max over
the parameters, at the figure's stated coverage: ``model_error_bound_pct``, two of
its 1 sigma, the bound "within accuracy" is judged by) beside the true largest
error and whether predicted >= true,
and PASS / FAIL (the criteria that failed in brackets); then cases passed / run
and the total runtime. Then ``--ethercat-runs`` default ``sidbe`` runs (1 ms
tick, time stamp, idle) against the EtherCAT slave served WITHOUT real-time
priority, each run's worst parameter error.

Targets (issue 28): M, B and each Coulomb level within 0.5 % with time stamps,
within 1 % without (2 % at a 2 ms tick); fit >= 99 %; |delay - drive's mean
delay| <= max(0.05 ms, tick / 10); no run stopped early (every log of the run
``status = complete``); predicted model error (two sigma) >= true error (or the true one
below 0.01 %, the registers' rounding: stamps in 1 us, velocity in 1e-6 steps). The 10 EtherCAT
runs without real-time priority within 0.5 % each.

``--drift PPM`` (default 0) serves every drive with a clock that runs PPM
parts per million fast against the host's (``serve-sim --drift``), as a real
drive's crystal does: its ticks slide against the host's cycle along the run.

Run: ``python benchmarks/drive_clock.py [--quick] [--transports modbus-tcp,canopen]
[--ticks 0.001,0.00025] [--loads idle,busy,stall] [--stamps yes,no] [--repeat N]
[--drift PPM] [--ethercat-runs N]``. The full matrix takes about an hour. ``--ethercat-runs``
defaults to 10 when ``ethercat`` is among the transports, else 0.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks.* (a namespace package)

from benchmarks.realtime import DRIVE_PRIORITY, NO_STAMP_EVER, busy, sim_url  # noqa: E402
from servobench.bench.testing import ethercat_link  # noqa: E402
from servobench.bench.testing.served import ServedSim  # noqa: E402

TRUTH = {"M": 0.01, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}
PARAMS = tuple(TRUTH)
TRANSPORTS = ("modbus-tcp", "modbus-rtu", "serial", "canopen", "ethercat")
TICKS_S = (0.000125, 0.00025, 0.0005, 0.001, 0.002)
#: Transports served at a 1 ms tick only (the issue's matrix).
ONE_MS_ONLY = frozenset({"canopen", "ethercat"})
QUICK_ARGS = ["--periods", "2", "--period", "2"]  # realtime.py --quick
SIDBE_TIMEOUT_S = 900.0
#: Load ``stall``: the host stopped every 0.5-1.5 s for 30-150 ms [s], beside the busy processes.
STALL_EVERY_S = (0.5, 1.5)
STALL_FOR_S = (0.03, 0.15)
ETHERCAT_RUNS = 10
CHILD_FLAG = "--ethercat-child"
RESULT_MARK = "DRIVE-CLOCK-RESULT "


# ------------------------------------------------------------------ one run
#: Errors below this [%] (a fiftieth of the 0.5 % target) are the rounding of the registers (stamps in
#: 1 us, velocity in 1e-6 steps): there the prediction need not cover the error, both being rounding.
EXACT_PCT = 1e-2


def covered(r: dict) -> bool:
    """The predicted model error covers the true one (or both are below :data:`EXACT_PCT`)."""
    pred = r.get("pred")
    if pred is None:
        return False
    return pred >= r["true"] or r["true"] < EXACT_PCT


def sidbe(url: str, out: Path, extra: list[str], stalls: bool = False) -> dict[str, object]:
    """``servobench sidbe --drive url --json --no-plots --out out *extra``: rc, stdout, stderr;
    with ``stalls`` the host process is stopped now and then as it runs (:func:`host_stalls`)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "servobench", "sidbe", "--drive", url, "--json", "--no-plots",
         "--out", str(out), *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    stopper = threading.Thread(target=host_stalls, args=(proc,), daemon=True) if stalls else None
    if stopper is not None:
        stopper.start()
    try:
        stdout, stderr = proc.communicate(timeout=SIDBE_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        return {
            "rc": None,
            "stdout": "",
            "stderr": f"sidbe did not end within {SIDBE_TIMEOUT_S:g} s",
        }
    finally:
        if stopper is not None:
            stopper.join()
    return {"rc": proc.returncode, "stdout": stdout, "stderr": stderr[-4000:]}


def host_stalls(proc: subprocess.Popen, seed: int | None = None) -> None:
    """Until ``proc`` ends: every :data:`STALL_EVERY_S` (uniform) stop it (SIGSTOP) for
    :data:`STALL_FOR_S` (uniform), then let it go on (SIGCONT): a host the machine stops now
    and then mid-exchange (load ``stall``), as a loaded suite's workers and a hypervisor do."""
    rng = random.Random(seed)
    while proc.poll() is None:
        time.sleep(rng.uniform(*STALL_EVERY_S))
        try:
            proc.send_signal(signal.SIGSTOP)
            time.sleep(rng.uniform(*STALL_FOR_S))
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGCONT)


def _ethercat_child(spec: dict) -> None:
    """Inside the namespace: the veth pair, the served slave (priority as given), one sidbe.
    As ``ethercat_link._child`` but for the slave's priority, which that child cannot omit."""
    iface_m, iface_s = ethercat_link.MASTER_IFACE, ethercat_link.SLAVE_IFACE
    for cmd in (
        ["ip", "link", "add", iface_m, "type", "veth", "peer", "name", iface_s],
        ["ip", "link", "set", iface_m, "up"],
        ["ip", "link", "set", iface_s, "up"],
    ):
        subprocess.run(cmd, check=True)
    ethercat_link._wait_for_carrier(iface_m)
    ethercat_link._wait_for_carrier(iface_s)
    with ServedSim("ethercat", spec["sim"], ["--iface", iface_s, *spec["serve_args"]],
                   priority=spec["priority"]) as served:  # fmt: skip
        result = sidbe(served.url, Path(spec["out"]), spec["extra"])
    print(RESULT_MARK + json.dumps(result), flush=True)


def sidbe_on_ethercat(sim: str, serve_args: list[str], priority: int | None, out: Path,
                      extra: list[str]) -> dict[str, object]:  # fmt: skip
    """One sidbe through a slave served on a private link (:mod:`ethercat_link`'s namespace)."""
    spec = {
        "sim": sim,
        "serve_args": serve_args,
        "priority": priority,
        "out": str(out),
        "extra": extra,
    }
    cmd = [*ethercat_link._unshare(), sys.executable, str(Path(__file__).resolve()), CHILD_FLAG,
           json.dumps(spec)]  # fmt: skip
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=SIDBE_TIMEOUT_S + 60)
    except subprocess.TimeoutExpired:
        return {"rc": None, "stdout": "", "stderr": "the EtherCAT link child did not end in time"}
    for line in done.stdout.splitlines():
        if line.startswith(RESULT_MARK):
            return json.loads(line[len(RESULT_MARK) :])
    return {"rc": None, "stdout": "", "stderr": f"EtherCAT link child exited {done.returncode}: "
            + (done.stderr.strip().splitlines() or ["no output"])[-1]}  # fmt: skip


def _status(log: str) -> str:
    """The last ``# status = ...`` of a log (the trailer's when it was written)."""
    status = "missing"
    try:
        with open(log, encoding="utf-8") as f:
            for line in f:
                if line.startswith("# status ="):
                    status = line.split("=", 1)[1].strip()
    except OSError:
        pass
    return status


def one(transport: str, tick_s: float, stamps: bool, seed: int, out: Path, extra: list[str],
        priority: int | None = DRIVE_PRIORITY, drift_ppm: float = 0.0, stalls: bool = False) -> dict[str, object]:  # fmt: skip
    """One ``sidbe`` through ``transport`` served at tick ``tick_s`` (its clock ``drift_ppm``
    fast; the host stopped now and then with ``stalls``); its figures and verdict."""
    stamps = stamps and transport not in NO_STAMP_EVER
    state = out.with_suffix(".state.json")
    serve_args = ["--clock", "real", "--tick", f"{tick_s:g}", "--state-file", str(state)]
    if drift_ppm:
        serve_args += ["--drift", f"{drift_ppm:g}"]
    if priority is not None:
        serve_args += ["--rt-priority", str(priority)]
    if not stamps and transport not in NO_STAMP_EVER:
        serve_args.append("--no-timestamp")
    sim = sim_url(TRUTH) + f"&seed={seed}"
    row: dict[str, object] = {"transport": transport, "tick": tick_s, "stamps": stamps}
    load = os.getloadavg()[0]
    t0 = time.monotonic()
    try:
        if transport == "ethercat":
            res = sidbe_on_ethercat(sim, serve_args, priority, out, extra)
        else:
            with ServedSim(transport, sim, serve_args, priority=priority) as served:
                res = sidbe(served.url, out, extra, stalls)
    except Exception as err:  # the served drive did not start: one line, go on
        res = {"rc": None, "stdout": "", "stderr": f"{type(err).__name__}: {err}"}
    row["wall_s"] = time.monotonic() - t0
    row["load"] = max(load, os.getloadavg()[0])
    try:
        model = json.loads(res["stdout"])
    except (TypeError, ValueError):
        model = {}
    if not isinstance(model, dict) or "M" not in model:  # no model: sidbe's one line, or {"error": ...}
        lines = str(res["stderr"]).strip().splitlines()
        row["error"] = (model.get("error") if isinstance(model, dict) else None) or (
            lines[-1] if lines else f"exit {res['rc']}")
        return row
    try:
        record = json.loads(state.read_text())["tick"]
    except (OSError, ValueError, KeyError):
        record = {}
    timing = model.get("timing") or {}
    row["errors"] = {k: 100 * (model[k] / v - 1) for k, v in TRUTH.items()}
    row["fit"] = model["fit_percent"]
    row["delay"] = model.get("delay_s")
    row["delay_std"] = (model.get("std") or {}).get("delay_s", timing.get("delay_std_s"))
    # over the commands that changed the value: a repeat acts alike from either tick, and a log
    # can tell no other (the two means agree where every command acts alike)
    row["drive_delay"] = record.get("mean_change_delay_s", record.get("mean_delay_s"))
    row["repeated"] = timing.get("repeated_samples")
    row["skipped"] = timing.get("skipped_ticks")
    row["late"] = timing.get("late_samples")  # EtherCAT: rows read a SYNC0 event late (t_act)
    # the prediction at the figure's stated coverage (two of its 1 sigma): what "within accuracy"
    # is judged by; at one sigma an honest prediction falls short in a third of the runs
    row["pred"] = timing.get("model_error_bound_pct")
    row["true"] = max(abs(e) for e in row["errors"].values())
    logs = [it.get("log", "") for it in model.get("iterations", [])] or [model.get("log", "")]
    row["stopped"] = [s for s in map(_status, logs) if s != "complete"] + [
        it["error"] for it in model.get("iterations", []) if it.get("error")
    ]
    row["failed"] = judge(row)
    return row


def tolerance_pct(stamps: bool, tick_s: float) -> float:
    if stamps:
        return 0.5
    return 2.0 if tick_s >= 0.002 - 1e-12 else 1.0


def judge(r: dict[str, object]) -> list[str]:
    """The acceptance criteria the run failed (empty: PASS)."""
    failed = []
    tol = tolerance_pct(bool(r["stamps"]), float(r["tick"]))
    failed += [k for k in PARAMS if not abs(r["errors"][k]) <= tol]
    if not r["fit"] >= 99.0:
        failed.append("fit")
    d, dd = r["delay"], r["drive_delay"]
    if d is None or dd is None or not abs(d - dd) <= max(0.05e-3, float(r["tick"]) / 10):
        failed.append("delay")
    if r["stopped"]:
        failed.append("stopped")
    if not covered(r):
        failed.append("pred<true")
    return failed


# ------------------------------------------------------------------ printing
def _ms(value, fmt: str = ".4f") -> str:
    return "-" if value is None or not math.isfinite(value) else format(value * 1e3, fmt)


HEAD = (f"{'transport':<10} {'tick ms':>7} {'stamp':>5} {'load':>5} {'M %':>8} {'B %':>8} {'Fc+ %':>8} "
        f"{'Fc- %':>8} {'fit %':>7} {'delay ms +- sd':>17} {'drive ms':>8} {'diff ms':>8} {'rep':>4} "
        f"{'skip':>5} {'late':>4} {'pred2s %':>8} {'true %':>8} {'p>=t':>4}  verdict  {'s':>4} {'lavg':>4}")  # fmt: skip


def print_row(r: dict[str, object], load_name: str) -> None:
    head = (f"{r['transport']:<10} {float(r['tick']) * 1e3:>7g} {'yes' if r['stamps'] else 'no':>5} "
            f"{load_name:>5}")  # fmt: skip
    if "error" in r:
        print(f"{head}  FAIL: {str(r['error'])[:140]}  ({r['wall_s']:.0f} s, load {r['load']:.1f})")
        return
    e = r["errors"]
    d, dd = r["delay"], r["drive_delay"]
    diff = d - dd if d is not None and dd is not None else None
    pred = r["pred"] if r["pred"] is not None else math.nan
    verdict = "PASS" if not r["failed"] else f"FAIL({','.join(r['failed'])})"
    print(
        f"{head} {e['M']:>8.4f} {e['B']:>8.4f} {e['coulomb_pos']:>8.4f} {e['coulomb_neg']:>8.4f} "
        f"{r['fit']:>7.3f} {_ms(d):>8} +- {_ms(r['delay_std'], '.4f'):<6} {_ms(dd):>8} {_ms(diff):>8} "
        f"{r['repeated']!s:>4} {r['skipped']!s:>5} {r['late']!s:>4} {pred:>8.3g} {r['true']:>8.3g} "
        f"{'yes' if covered(r) else 'no':>4}  {verdict:<7}  {r['wall_s']:>4.0f} {r['load']:>4.1f}"
    )


def _keep(out: Path, into: Path) -> None:
    """Copy a failed case's run folder ``out`` and its drive record (``out``.state.json) into ``into``."""
    into.mkdir(parents=True, exist_ok=True)
    if out.is_dir():
        shutil.copytree(out, into / out.name, dirs_exist_ok=True)
    state = out.with_suffix(".state.json")
    if state.exists():
        shutil.copy2(state, into / f"{out.name}.state.json")
    print(f"  kept in {into / out.name}")


# ------------------------------------------------------------------ main
def _list(text: str) -> list[str]:
    return [s.strip() for s in text.split(",") if s.strip()]


def main() -> None:
    if len(sys.argv) > 2 and sys.argv[1] == CHILD_FLAG:
        _ethercat_child(json.loads(sys.argv[2]))
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="a shorter excitation (2 periods of 2 s per run, as realtime.py --quick)")  # fmt: skip
    ap.add_argument("--transports", default=",".join(TRANSPORTS))
    ap.add_argument("--ticks", default=",".join(f"{t:g}" for t in TICKS_S),
                    help="drive ticks [s] (canopen and ethercat run at 0.001 only)")  # fmt: skip
    ap.add_argument("--loads", default="idle,busy",
                    help="idle,busy (default), and stall: busy, the host stopped 30-150 ms every 0.5-1.5 s")  # fmt: skip
    ap.add_argument("--stamps", default="yes,no")
    ap.add_argument("--repeat", type=int, default=1, help="runs per case")
    ap.add_argument("--drift", type=float, default=0.0, metavar="PPM",
                    help="every served drive's clock runs PPM parts per million fast (default 0)")  # fmt: skip
    ap.add_argument("--keep-failed", type=Path, default=None, metavar="DIR",
                    help="copy each failed case's run folder and the served drive's record here")  # fmt: skip
    ap.add_argument("--keep-all", type=Path, default=None, metavar="DIR",
                    help="copy every case's run folder and the served drive's record here")  # fmt: skip
    ap.add_argument("--ethercat-runs", type=int, default=None,
                    help="default sidbe runs against the EtherCAT slave without real-time priority "
                    f"(default {ETHERCAT_RUNS} when ethercat is among the transports, else 0)")  # fmt: skip
    args = ap.parse_args()
    transports = _list(args.transports)
    unknown = sorted(set(transports) - set(TRANSPORTS))
    if unknown:
        ap.error(f"unknown transports {unknown}; choose from {','.join(TRANSPORTS)}")
    ticks = [float(t) for t in _list(args.ticks)]
    loads = _list(args.loads)
    if "stall" in loads and "ethercat" in transports:
        print("ethercat: no stall load (its host runs inside the link's namespace): idle and busy only")
    stamps = [s == "yes" for s in _list(args.stamps)]
    extra = QUICK_ARGS if args.quick else []
    ecat_runs = args.ethercat_runs
    if ecat_runs is None:
        ecat_runs = ETHERCAT_RUNS if "ethercat" in transports else 0
    start = time.monotonic()
    no_link = ethercat_link.link_unavailable() if "ethercat" in transports or ecat_runs else None
    if no_link is not None:
        print(f"EtherCAT not run: no private EtherCAT link here: {no_link}")
        transports = [t for t in transports if t != "ethercat"]
        ecat_runs = 0
    for t in sorted(ONE_MS_ONLY & set(transports)):
        if not any(math.isclose(x, 0.001) for x in ticks):
            print(f"{t}: served at a 1 ms tick only, and --ticks has no 0.001: not run")
    print(f"excitation: {'2 periods x 2 s per run' if args.quick else 'default'}; plant {sim_url(TRUTH)}"
          f"&seed=N; drive clock drift {args.drift:g} ppm; {os.cpu_count()} CPUs; load average at start "
          f"{os.getloadavg()[0]:.1f}")  # fmt: skip
    print(HEAD)
    passed = ran = 0
    seed = 0
    with tempfile.TemporaryDirectory() as tmp:
        for load_name in loads:
            with busy(load_name in ("busy", "stall")):
                for transport in transports:
                    for tick_s in ticks:
                        if transport in ONE_MS_ONLY and not math.isclose(tick_s, 0.001):
                            continue
                        if load_name == "stall" and transport == "ethercat":
                            continue
                        for stamp in stamps:
                            if stamp and transport in NO_STAMP_EVER:
                                continue
                            for _ in range(args.repeat):
                                seed += 1
                                out = (
                                    Path(tmp) / f"{transport}-{tick_s:g}-{stamp}-{load_name}-{seed}"
                                )
                                r = one(transport, tick_s, stamp, seed, out, extra, drift_ppm=args.drift,
                                        stalls=load_name == "stall")  # fmt: skip
                                print_row(r, load_name)
                                if args.keep_failed and ("error" in r or r["failed"]):
                                    _keep(out, args.keep_failed)
                                if args.keep_all:
                                    _keep(out, args.keep_all)
                                sys.stdout.flush()
                                ran += 1
                                passed += "error" not in r and not r["failed"]
        print(f"cases passed: {passed} / {ran}")
        if ecat_runs:
            print(f"EtherCAT, {ecat_runs} default sidbe runs, tick 1 ms, time stamp, idle, served slave "
                  "WITHOUT real-time priority (no --rt-priority):")  # fmt: skip
            worst_all, good = 0.0, 0
            for k in range(ecat_runs):
                seed += 1
                out = Path(tmp) / f"ethercat-nort-{seed}"
                r = one("ethercat", 0.001, True, seed, out, [], priority=None)
                if "error" in r:
                    print(f"  run {k + 1:>2}: FAIL: {str(r['error'])[:140]} ({r['wall_s']:.0f} s)")
                    continue
                name = max(PARAMS, key=lambda p: abs(r["errors"][p]))
                worst = abs(r["errors"][name])
                worst_all = max(worst_all, worst)
                good += worst <= 0.5
                print(f"  run {k + 1:>2}: worst parameter error {worst:.3g} % ({name}), predicted {r['pred'] or math.nan:.3g} % (2 sigma), fit {r['fit']:.3f} %, "
                      f"delay {_ms(r['delay'])} ms vs drive {_ms(r['drive_delay'])} ms, "
                      f"{r['late']} rows read late, "
                      f"{'PASS' if not r['failed'] else 'FAIL(' + ','.join(r['failed']) + ')'} "
                      f"({r['wall_s']:.0f} s, load {r['load']:.1f})")  # fmt: skip
                sys.stdout.flush()
            print(f"EtherCAT without real-time priority: {good} / {ecat_runs} runs within 0.5 %, "
                  f"worst {worst_all:.3g} %")  # fmt: skip
    print(f"total runtime {time.monotonic() - start:.0f} s")


if __name__ == "__main__":
    main()
