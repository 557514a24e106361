"""A drive with its own clock (issue 28): default ``sidbe`` against served drives that tick.

Each served drive runs its physics on its own control tick (``serve-sim
--tick``), asynchronous to the host, from a random phase: a command acts
from the drive's next tick, a read returns its last tick's sample. The host
streams a short SIDBE excitation (two periods of 1 s per run; 2 s on Modbus RTU) in real time
through the real protocol stack, with and without the drive's time stamp,
and identifies the axis. The plant is M 0.01, B 1, Coulomb 0.5 / 0.4 (a
time constant of 10 ms, so a 1 ms tick left unmodelled costs M about 30 %).
Two Modbus TCP cases serve a drive whose clock drifts against the host's
(:data:`DRIFT_PPM`, ``serve-sim --drift``), as every real drive's does.
Every served transport: Modbus TCP, Modbus RTU, CANopen and ODrive serial
here, and the EtherCAT slave on a private link of its own
(:data:`ETHERCAT_CASES`), DC-synchronous at a 1 ms SYNC0 with the drive's tick
inside its cycle: the sample the last tick's before the event, the command
latched at the event acting from the next tick.

Judged per case, the issue's bounds: M, B and each Coulomb level within
0.5 % with stamps and 1 % without; fit >= 99 %;
the identified delay within 0.05 ms (or a tenth of the tick) of the mean
delay the served drive's own record shows over the commands that changed the
value (on Modbus RTU without stamps where no tick grid is located, three of
its stated sigma where that is wider: its 50 Hz cannot always find a 0.25 ms
tick in a short run, open); the run complete; a predicted model error at its
stated coverage (``model_error_bound_pct``, two sigma) that covers the true one; and a timing figure that says what it saw (the delay, and with
stamps the tick and the repeated reads).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from servobench.bench.testing.ethercat_link import link_unavailable, run_on_link
from servobench.bench.testing.served import PATIENT_KEYS, ServedSim
from servobench.bench.testing.sidbe_run import sidbe_json

#: one real-time bench at a time over the workers (conftest.realtime_bench)
pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("realtime_bench")]

TRUE = {"M": 0.01, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}
PLANT = "sim://?M=0.01&B=1&fc_pos=0.5&fc_neg=0.4&seed={seed}"
#: Two periods of 1 s per run; 2 s on Modbus RTU, whose link carries 50 Hz (:func:`short`).
SHORT = ["--periods", "2", "--period", "1"]


def short(transport: str) -> list[str]:
    """The excitation's options on ``transport``: :data:`SHORT`, its periods twice as long on
    Modbus RTU, whose 50 Hz then still gives each run 200 samples."""
    return ["--periods", "2", "--period", "2"] if transport == "modbus-rtu" else SHORT


CASES = [
    (transport, tick, stamps)
    for transport in ("modbus-tcp", "modbus-rtu", "canopen", "serial")
    for tick in (1e-3, 2.5e-4)
    for stamps in (True, False)
    if not (transport == "serial" and stamps)  # the ODrive protocol has no time stamp
]
#: Drive clocks that drift against the host's [ppm] (``serve-sim --drift``): a crystal 100 ppm
#: slow without stamps (the tick grid located on the host's clock slides along the run), and a
#: ceramic resonator 4000 ppm fast with them (on the stamps as they are M would be 0.4 % large:
#: here it must be within 0.1 %, taken onto the host's seconds, with the drift in the timing
#: figure). The other cases keep the host's rate.
DRIFT_PPM = {("modbus-tcp", 1e-3, False): -100.0, ("modbus-tcp", 1e-3, True): 4000.0}
#: The served EtherCAT slave (on a private link: ``bench.testing.ethercat_link``), its SYNC0 at
#: 1 ms, with its DC time stamp (0x10F8) and without; the drive's tick inside the SYNC0 cycle.
ETHERCAT_CASES = [(tick, stamps) for tick in (1e-3, 2.5e-4) for stamps in (True, False)]


def _sidbe(transport: str, tick: float, stamps: bool, tmp_path: Path, seed: int,
           drift_ppm: float = 0.0) -> tuple[dict, dict]:  # fmt: skip
    state = tmp_path / "state.json"
    args = ["--clock", "real", "--tick", str(tick), "--state-file", str(state)]
    if drift_ppm:
        args += ["--drift", str(drift_ppm)]
    if not stamps and transport != "serial":
        args.append("--no-timestamp")
    with ServedSim(transport, PLANT.format(seed=seed), args) as served:
        out = sidbe_json(served.url + PATIENT_KEYS[transport], ["--no-plots", *short(transport)])
    assert out["rc"] == 0, out["stderr"].strip().splitlines()[-1:]
    return json.loads(out["stdout"]), json.loads(state.read_text())["tick"]


@pytest.mark.parametrize(("transport", "tick", "stamps"), CASES,
                         ids=[f"{t}-{k * 1e3:g}ms-{'stamps' if s else 'nostamp'}" for t, k, s in CASES])  # fmt: skip
def test_default_sidbe_on_a_drive_that_ticks(transport, tick, stamps, tmp_path):
    drift = DRIFT_PPM.get((transport, tick, stamps), 0.0)
    model, record = _sidbe(transport, tick, stamps, tmp_path, seed=CASES.index((transport, tick, stamps)),
                           drift_ppm=drift)  # fmt: skip
    _judge(transport, tick, stamps, model, record, drift)


def link_sidbe_short(iface: str, url: str) -> dict:
    """Inside the private link's namespace: the short ``sidbe`` on the slave's URL as printed."""
    return sidbe_json(url, ["--no-plots", *SHORT])


@pytest.mark.parametrize(("tick", "stamps"), ETHERCAT_CASES,
                         ids=[f"{k * 1e3:g}ms-{'stamps' if s else 'nostamp'}" for k, s in ETHERCAT_CASES])  # fmt: skip
def test_default_sidbe_on_an_ethercat_slave_that_ticks(tick, stamps, tmp_path):
    """The served EtherCAT slave on a private link, DC-synchronous at a 1 ms SYNC0, its drive
    ticking inside it: the same bounds as every other transport."""
    why = link_unavailable()
    if why is not None:  # a failure to fix (run as root, or allow user namespaces), never a skip
        pytest.fail(f"no private EtherCAT link: {why}")
    state = tmp_path / "state.json"
    args = ["--clock", "real", "--tick", str(tick), "--state-file", str(state)]
    seed = len(CASES) + ETHERCAT_CASES.index((tick, stamps))
    out = run_on_link(__file__, "link_sidbe_short", PLANT.format(seed=seed),
                      args + ([] if stamps else ["--no-timestamp"]))  # fmt: skip
    assert out["rc"] == 0, out["stderr"].strip().splitlines()[-1:]
    model = json.loads(out["stdout"])
    _judge("ethercat", tick, stamps, model, json.loads(state.read_text())["tick"], 0.0)
    assert model["timing"]["late_samples"] is not None  # the log says where each command acted
    # with 0x10F8 the stamps; without it (nor 0x1013) the SYNC0 event before each frame
    clock = "0x10F8 DC system time of each sample" if stamps else "DC system time of each sample (the SYNC0 event"
    assert f"# drive_clock = {clock}" in out["heads"]["log.csv"], out["heads"]


def _judge(transport: str, tick: float, stamps: bool, model: dict, record: dict, drift: float) -> None:
    """The issue's bounds on one run (the module docstring)."""
    bound = 0.5 if stamps else 1.0
    fit_floor = 99.0
    errors = {k: 100.0 * (model[k] / v - 1.0) for k, v in TRUE.items()}
    seen = {"errors": errors, "fit": model["fit_percent"], "timing": model["timing"], "record": record,
            "std": model["std"], "estimator": model["estimator"], "selection": model.get("selection"),
            "notes": model.get("notes")}  # fmt: skip
    print("seen:", json.dumps(seen, default=str))  # what a failure shows, whole
    worst = max(abs(e) for e in errors.values())
    # every transport is held to the bounds. Modbus RTU without stamps (50 Hz, brackets of +-1.3 ms)
    # had passed beyond them where its figure said so (a fresh-clone suite once gave 3.6 % at 1 ms,
    # on earlier code); its two cases here, 76 runs at stop 58's and 59's code (24 idle, 32 beside
    # two busy processes, 20 with the host stopped 30-150 ms every 0.5-1.5 s as well), were all
    # within 0.16 %, fits 99.76 % or more. Modbus TCP, CANopen and EtherCAT: 40 runs of the Modbus
    # TCP and CANopen cases beside busy processes, half with the host stopped, within 0.011 % (the
    # drifting clock's 0.010 %), fits 99.996 % or more; the benchmark's EtherCAT runs without stamps
    # within 1.2e-5 %. ODrive serial (200 Hz) since its output error leaves the samples of stalled
    # exchanges out and reads all in doubt keep the model's residual scale: 18 runs of its two cases
    # (6 idle, 6 beside two busy processes, 6 with the host stopped as well), each delay within
    # 0.026 ms of the record, each model within 0.8 %
    assert worst <= bound, seen
    # the fit floor where the loaded suite stalled the host too: the samples of exchanges
    # it stalled in, and those a command sent in one may have moved, are left out of the fit (a
    # fresh-clone suite had given ODrive serial at 1 ms, host stalls of 74 ms, a fit of 98.91 % for
    # a model within 0.11 %, and Modbus TCP at 1 ms, a 5.4 ms stall, 98.43 % within 0.006 %)
    timing = model["timing"]
    assert model["fit_percent"] >= fit_floor, seen
    near = max(0.05e-3, tick / 10)  # the bound
    located = any("control tick" in n and "located" in n for n in model.get("notes", ()))
    if transport == "modbus-rtu" and not stamps and not located:
        # NOT the bound where no tick grid is located (open): at the 50 Hz its link
        # carries, brackets of +-1.3 ms, a short run's constant delay came out 0.14-0.34 ms against
        # the record's 0.25 at a 0.25 ms tick (4 of the 16 runs at stop 59's code that located no
        # grid there; 0.094 and 0.111 ms off in two), within three of its stated sigma (0.07-0.35
        # ms); on a located grid the delay is held at its whole ticks: the record's (within 0.0002
        # ms) in each of the 28 runs at stop 59's code that located one
        near = max(near, 3.0 * model["std"]["delay_s"])
    # the record's mean over the commands that changed the value: a repeat acts alike from
    # either tick (the command and the query as two requests: a tick falls between them in some
    # rows), so only a change shows its delay; where every command acts alike, the two means agree
    assert abs(model["delay_s"] - record["mean_change_delay_s"]) <= near, (model["delay_s"], record)
    assert model["std"]["delay_s"] is not None and model["std"]["delay_s"] > 0
    assert timing["delay_s"] == pytest.approx(model["delay_s"])
    # the verdict follows the figure: a fit over the threshold is a plain pass only within accuracy
    assert model["verdict"] == ("pass" if timing["within_accuracy"] else "pass with remarks"), timing
    # the predicted model error at its stated coverage (two of its 1 sigma, the bound "within
    # accuracy" is judged by) covers the true one; at one sigma an honest prediction falls short in
    # a third of the runs (a fresh-clone suite: ODrive serial at 1 ms, host stalls of 97 ms,
    # 3.58 % off with 3.30 % predicted at 1 sigma). Errors below 0.01 % are not judged, as in the
    # benchmark (with stamps the models are exact to 1e-4 %). Without stamps this was a fiftieth of
    # the stated accuracy, 0.02 %, after a fresh-clone suite gave CANopen at 1 ms 0.0123 % off with
    # 0.0011 % predicted (misplaced reads the figure's draws did not reproduce). CANopen now
    # predicts about 0.058 % there, and 104 runs of the cases without stamps beside busy
    # processes, half of them with the host stopped now and then, each predicted at least its
    # error
    floor = 0.01
    # at two sigma where the host stalled too (a fresh-clone suite had given ODrive serial at 1 ms,
    # a 28 ms stall, M 0.74 % off with 0.51 % predicted, before a command sent in a stalled
    # exchange weighed the samples after it)
    assert timing["model_error_bound_pct"] >= worst or worst < floor, (
        timing["model_error_pct"], errors)  # fmt: skip
    assert record["drift_ppm"] == pytest.approx(drift)
    if stamps and drift:
        assert abs(errors["M"]) <= 0.1, errors  # in the host's seconds, not the drive's
        drifted = timing["drive_drift_ppm"]
        assert abs(drifted - drift) <= 4.0 * timing["drive_drift_std_ppm"], timing
    if stamps or transport == "ethercat":  # without 0x10F8, each frame's SYNC0 event is the clock
        assert model["clock_source"] == "drive"
        # the stamps show the drive's grid: the tick itself, or the coarsest grid they were read on
        assert timing["drive_tick_s"] is not None
        assert timing["drive_tick_s"] / tick == pytest.approx(round(timing["drive_tick_s"] / tick), abs=1e-3)
    else:
        assert model["clock_source"] != "drive"

