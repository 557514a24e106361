"""Issue 11: limited-travel axes are excited in closed loop and identified without bias.

``sidbe`` with default options on ``sim://`` plants with noise and a travel
window: the hold loop keeps every logged position inside the window, the log
carries ``u`` (total), ``u_exc``, ``x_ref`` and ``loop = closed``, and the
model is within 1 % (pole, DC gain) and 5 % (Coulomb) of the plant. On the
host's loop, on the simulated drive's own loop, and on an EMPS-sized axis.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import replace

import numpy as np
import pytest

import servobench.drivers.registry
from servobench.bench.cli import main
from servobench.bench.identify.dataset import prepare
from servobench.bench.identify.joint import identify_joint
from servobench.bench.identify.regression import fit_pairs, select_pairs
from servobench.bench.log.io import ExperimentLog, read_log
from servobench.bench.model.servo import ServoModel
from servobench.bench.procedure.excitation import design_excitation, freqs_from, make_design
from servobench.bench.procedure.sidbe import SidbeOptions, run_sidbe
from servobench.bench.report.plot_data import frf_evidence
from servobench.bench.run.closed import stream_closed_runs
from servobench.bench.run.hold import HoldController, HoldLoop, design_hold
from servobench.bench.run.travel import MARGIN, ClosedLoopPlan
from servobench.drivers.registry import open_drive
from servobench.drivers.sim import SimDrive
from servobench.errors import LimitExceededError, notes_of
from servobench.sim_backend.device import PowerState
from servobench.sim_backend.physics.coulomb import PlantParams, PlantState, simulate_coulomb

WINDOW = "&xmin=-0.05&xmax=0.05"


def check_model(model: dict, M: float, B: float, fc_pos: float, fc_neg: float) -> None:
    assert model["pole"] == pytest.approx(-B / M, rel=0.01)
    assert model["dc_gain"] == pytest.approx(1 / B, rel=0.01)
    assert model["coulomb_pos"] == pytest.approx(fc_pos, rel=0.05)
    assert model["coulomb_neg"] == pytest.approx(fc_neg, rel=0.05)


def check_closed_log(path, xmin: float, xmax: float) -> ExperimentLog:
    """Every logged x inside the window; the closed-loop columns and metadata."""
    log = read_log(path)
    assert log.complete and [r.run for r in log.runs] == [1, 2]
    assert log.metadata["loop"] == "closed" and float(log.metadata["hold_kp"]) > 0
    for r in log.runs:
        assert xmin < r.x.min() and r.x.max() < xmax
        assert r.u_exc is not None and r.x_ref is not None
        assert not np.allclose(r.u, r.u_exc)  # u is the total: the hold loop's share included
        level = float(log.metadata["amplitude"]) * (1.0 if r.run == 1 else 0.9)
        np.testing.assert_allclose(np.abs(r.u_exc), level, rtol=1e-9)  # the binary excitation
    return log


def test_sidbe_defaults_on_a_window_of_five_hundredths(tmp_path, capsys):
    out = tmp_path / "run"
    rc = main(["sidbe", "--drive", "sim://?noise=0.01&seed=1" + WINDOW, "--json", "--out", str(out),
               "--no-plots"])  # fmt: skip
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    model = json.loads(captured.out)
    check_model(model, 0.1, 1.0, 0.5, 0.4)
    assert model["loop"] == "closed" and model["hold"]["where"] == "host"
    assert 0 < model["hold"]["travel_share"] <= MARGIN
    assert model["method"] == "joint" and "auto: joint, validation fit" in model["selection"]
    log = check_closed_log(out / "log.csv", -0.05, 0.05)
    assert float(log.metadata["x_ref"]) == 0.0 and float(log.metadata["hold_bandwidth_hz"]) > 0
    probe = read_log(out / "probe.csv")  # the short first run is kept, inside the window too
    assert probe.complete and all(r.x.min() > -0.05 and r.x.max() < 0.05 for r in probe.runs)
    assert "relay probe" in model["files"]["probe.csv"] and "hold-trial.csv" not in model["files"]
    check_validate(out, model, capsys)


def _validate(model_path, log_path, capsys) -> dict:
    rc = main(["validate", str(model_path), str(log_path), "--json"])
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    assert rc == (3 if out.get("verdict") == "fail" else 0), captured.err  # the exit follows the verdict
    return out


def check_validate(out, model: dict, capsys) -> None:
    """``servobench validate`` reads the closed-loop log as closed loop (its ``# loop = closed``):
    identify's fit, and a force error as small as the plant's own on that log (the noise floor),
    while a model with twice the inertia is clearly worse."""
    got = _validate(out / "model.json", out / "log.csv", capsys)
    assert got["loop"] == "closed" and got["samples"] == 2 * 16000
    assert got["fit_percent"] == pytest.approx(model["fit_percent"], rel=1e-9)
    plant = {"M": 0.1, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}
    heavy = {**plant, "M": 0.2}
    errors = {}
    for name, params in (("plant", plant), ("heavy", heavy)):
        path = out.parent / f"{name}.json"
        path.write_text(json.dumps(params))
        errors[name] = _validate(path, out / "log.csv", capsys)["force_error_percent"]
    assert got["force_error_percent"] == pytest.approx(errors["plant"], abs=0.5)
    assert errors["heavy"] > 2 * errors["plant"]


def test_emps_sized_axis_with_a_tenth_of_a_metre(tmp_path):
    """Also the trap of reading a closed-loop log as open loop: the hold's command is not
    periodic (the loop answers the noisy motion), so one period of it against the averaged
    velocity biases B; the closed-loop estimator works on raw samples and is not biased."""
    plant = "sim://?M=95.1&B=203.5&fc_pos=17.2&fc_neg=23.6&noise=0.002&seed=2&max_u=300&units=linear"
    r = run_sidbe(open_drive(plant + "&xmin=-0.1&xmax=0.1"), SidbeOptions(plots=False), tmp_path)
    check_model(r.to_json(), 95.1, 203.5, 17.2, 23.6)
    log = check_closed_log(tmp_path / "log.csv", -0.1, 0.1)
    assert r.hold["probe"]["relay_amplitude"] > 23.6  # the probe found what breaks friction
    evidence = frf_evidence(r.result)  # the FRF plot's friction note: against the excitation
    assert evidence.amplitude == pytest.approx(r.design.amplitude, rel=1e-9)
    assert evidence.amplitude < np.max(np.abs(log.run(1).u))  # not the total, hold included
    data = prepare(log)
    closed = identify_joint(data)
    as_open = identify_joint(replace(data, closed_loop=False))
    assert "excitation as instrument" in closed.estimator and as_open.estimator == "output-error"
    assert abs(closed.model.B / 203.5 - 1) < 0.005 < 0.01 < abs(as_open.model.B / 203.5 - 1)


def test_the_drives_own_loop_holds_the_axis(tmp_path):
    """sim:// with pos_kp has a position loop of its own: the drive-side hold is used, its
    gains are fitted to a trial, and u is the total it reports applied."""
    url = "sim://?noise=0.01&seed=3&pos_kp=4&pos_ki=4&pos_kd=0.2" + WINDOW
    drive = open_drive(url)
    assert drive.supports_drive_hold
    r = run_sidbe(drive, SidbeOptions(plots=False, period_s=2.0, periods=3), tmp_path)
    check_model(r.to_json(), 0.1, 1.0, 0.5, 0.4)
    assert r.hold["where"] == "drive" and "gains fitted" in r.hold["drive_loop"]
    assert (r.hold["kp"], r.hold["ki"], r.hold["kd"]) == pytest.approx((4.0, 4.0, 0.2), rel=0.02)
    log = check_closed_log(tmp_path / "log.csv", -0.05, 0.05)
    assert log.metadata["hold"] == "drive" and log.metadata["pos_kp"] == "4"
    run = log.run(1)  # the drive's loop, recomputed from the logged feedback, is the rest of u
    e = run.x_ref - run.x
    integral = run.u - run.u_exc - (4.0 * e - 0.2 * run.v)  # ki times the sum of e dt
    np.testing.assert_allclose(np.diff(integral), 4.0 * e[1:] * 1e-3, rtol=0, atol=5e-9)
    assert (tmp_path / "hold-trial.csv").is_file() and "hold-trial.csv" in r.to_json()["files"]


def test_open_loop_on_unlimited_travel_is_as_before(tmp_path):
    r = run_sidbe(open_drive("sim://"), SidbeOptions(plots=False, periods=2, period_s=1.0), tmp_path)
    assert r.loop == "open" and r.hold is None and "hold" not in r.to_json()
    log = read_log(tmp_path / "log.csv")
    assert log.metadata["loop"] == "open" and log.runs[0].u_exc is None
    assert set(np.abs(log.runs[0].u)) == {1.0}
    assert not (tmp_path / "probe.csv").exists()


def test_open_loop_forced_on_a_window_still_leaves_it(tmp_path, capsys):
    rc = main(["sidbe", "--drive", "sim://?" + WINDOW[1:], "--loop", "open", "--out", str(tmp_path)])
    assert rc == 1
    assert "outside the allowed travel [-0.05, 0.05]" in capsys.readouterr().err


def _plan(model: ServoModel, bandwidth_hz: float, room: float, amplitude: float = 1.0) -> ClosedLoopPlan:
    design = make_design(amplitude, period_s=1.0, periods=2, freqs_hz=(3.0, 5.0, 8.0, 13.0))
    controller = HoldController(design_hold(model.M, model.B, bandwidth_hz), "host", 0.0, 1e-3)
    return ClosedLoopPlan(design, controller, room, 0.0, model)


def test_an_unstable_hold_stops_and_disables_the_axis_and_keeps_the_log(tmp_path):
    """A loop designed for an axis a hundred times lighter oscillates and grows on this one."""
    plan = _plan(ServoModel(10.0, 1.0, 0.5, 0.4), 3.0, 0.05)
    drive = open_drive("sim://" + "?" + WINDOW[1:])
    with drive, pytest.raises(LimitExceededError) as err:
        runs = design_excitation(plan.design).runs()
        stream_closed_runs(drive, runs, 1000.0, tmp_path / "log.csv", plan, settle_s=0.01)
    message = str(err.value)
    assert "could not keep it within 80% of its room" in message and "\n" not in message
    assert f"partial log kept in {tmp_path / 'log.csv'}" in message
    assert "Lower the amplitude, raise the lowest excited line, or widen xmin/xmax" in message
    assert not drive.enabled and drive.power_state is PowerState.DISABLED and drive.device.command == 0.0
    text = (tmp_path / "log.csv").read_text()
    assert "# status = incomplete" in text and "could not keep it" in text
    log = read_log(tmp_path / "log.csv")
    assert abs(log.runs[-1].x[-1]) > MARGIN * 0.05  # the breaching sample is logged too


def test_a_window_too_small_for_any_identifiable_excitation(tmp_path, capsys):
    rc = main(["sidbe", "--drive", "sim://?noise=0.01&seed=1&xmin=-0.002&xmax=0.002", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert rc == 1 and err.count("\n") == 1
    assert "the travel window is too small for an identifiable excitation" in err
    assert "widen the travel (xmin/xmax)" in err and f"probe log kept in {tmp_path / 'probe.csv'}" in err
    assert read_log(tmp_path / "probe.csv").complete and not (tmp_path / "log-1.csv").exists()


def test_the_excitation_is_the_instrument_of_the_command():
    """The classic closed-loop bias: the hold's velocity gain feeds the velocity noise into u,
    so u used as its own instrument biases the regression (M by about -6 % here); the
    excitation, which no noise reaches, does not. Instruments for v: the noise-free velocity."""
    params = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)
    gains = design_hold(params.M, params.B, 1.4)
    assert gains.kd > 1.0
    design = make_design(2.8, period_s=2.0, periods=4)
    u_exc = design_excitation(design.with_freqs(freqs_from(7.0, 1000.0, 2000))).u1
    errors: dict[str, list[float]] = {"own": [], "excitation": []}
    for seed in (0, 3, 4):
        loop = HoldLoop(HoldController(gains, "host", 0.0, 1e-3))
        noise = np.random.default_rng(seed).normal(0.0, 0.05, u_exc.size)
        state, u, v, v_true = PlantState(), *(np.empty(u_exc.size) for _ in range(3))
        for k, uk in enumerate(u_exc):
            v_true[k], v[k] = state.v, state.v + noise[k]
            u[k] = loop.command(uk, state.x, v[k])
            _, _, state = simulate_coulomb(np.array([u[k]]), 1e-3, params, state)
        intervals = [np.full(u.size - 1, 1e-3)]
        for name, excitations in (("own", None), ("excitation", [u_exc])):
            pairs = select_pairs([v], [u], intervals, references=[v_true], threshold=0.15,
                                 excitations=excitations)  # fmt: skip
            errors[name].append(fit_pairs(pairs, 1e-3, instrumental=True).M / params.M - 1)
    assert np.mean(errors["own"]) < -0.04
    assert abs(np.mean(errors["excitation"])) < 0.01


def test_closed_loop_needs_a_travel_to_hold_the_axis_in(tmp_path, capsys):
    rc = main(["run", "--drive", "sim://", "--loop", "closed", "--out", str(tmp_path / "log.csv")])
    err = capsys.readouterr().err
    assert rc == 1 and "give xmin/xmax in the drive URL, or run with --loop open" in err
    assert not (tmp_path / "log.csv").exists()


def test_a_folder_holding_an_earlier_probe_is_refused(tmp_path, capsys):
    """A closed-loop run that ended in its probe leaves only probe.csv: a new run must not
    overwrite it (the drive is not even opened: its URL names no reachable drive here)."""
    (tmp_path / "probe.csv").write_text("# loop = closed\nrun,t,u,v,x\n1,0,0,0,0\n")
    rc = main(["sidbe", "--drive", "modbus+tcp://127.0.0.1:9?unit=1", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert rc != 0 and "already holds a run (probe.csv)" in err and "nothing was overwritten" in err
    assert (tmp_path / "probe.csv").read_text().endswith("1,0,0,0,0\n")


class CtrlCAfter(SimDrive):
    """Ctrl-C arrives at the ``AFTER``-th cycle."""

    AFTER = 1000
    cycles = 0

    def _exchange(self, u):
        self.cycles += 1
        if self.cycles == self.AFTER:
            raise KeyboardInterrupt
        return super()._exchange(u)


def test_ctrl_c_in_a_closed_loop_round_stops_disables_and_names_the_partial_log(tmp_path):
    drive = CtrlCAfter("sim://?noise=0.01&seed=1" + WINDOW)
    drive.AFTER = 4000  # past the rest before the first run
    known = ServoModel(0.1, 1.0, 0.5, 0.4)  # as from a bump test: no probe
    with pytest.raises(KeyboardInterrupt) as err:
        run_sidbe(drive, SidbeOptions(plots=False), tmp_path, known=known)
    assert not drive.enabled and drive.power_state is PowerState.DISABLED
    log = read_log(tmp_path / "log-1.csv")
    assert not log.complete and log.metadata["reason"] == "interrupted (Ctrl-C)"
    assert log.metadata["loop"] == "closed"
    rows = sum(len(r) for r in log.runs)
    assert 0 < rows < 4000
    assert notes_of(err.value) == [f"partial log kept: {tmp_path / 'log-1.csv'} ({rows} samples, marked incomplete)"]


def test_ctrl_c_in_the_probe_names_the_probe_log(tmp_path, capsys, monkeypatch):
    made = []
    monkeypatch.setattr(servobench.drivers.registry, "open_drive",
                        lambda url: made.append(CtrlCAfter(url)) or made[-1])  # fmt: skip
    rc = main(["sidbe", "--drive", "sim://?noise=0.01&seed=1" + WINDOW, "--out", str(tmp_path / "run")])
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert rc == 130 and line.startswith("servobench: interrupted; axis stopped; partial log kept: ")
    assert str(tmp_path / "run" / "probe.csv") in line and not made[0].enabled
    assert read_log(tmp_path / "run" / "probe.csv").metadata["reason"] == "interrupted (Ctrl-C)"


class SyncPaced(SimDrive):
    """A drive whose exchange waits for its own next cycle, as a DC-synchronous EtherCAT slave's
    does (the outputs take force at the next SYNC0 event, the inputs are read after it), whose
    enable takes a while (state changes through the mailbox), and whose exchange costs the host
    0.6 ms more in every other block of 500 (a host that gets busy: the answer comes back later
    in the drive's cycle)."""

    ENABLE_S = 0.3
    CYCLE_S = 1e-3
    BLOCK = 500
    BUSY_S = 0.6e-3
    exchanges = 0

    def _enable(self) -> None:
        time.sleep(self.ENABLE_S)
        super()._enable()

    def _pace(self, cycles: int = 1) -> None:
        now = time.monotonic()
        time.sleep((math.floor(now / self.CYCLE_S) + 1) * self.CYCLE_S - now + 50e-6)
        self.exchanges += 1
        if (self.exchanges // self.BLOCK) % 2:
            end = time.monotonic() + self.BUSY_S
            while time.monotonic() < end:
                pass


def test_the_closed_loops_deadlines_start_after_the_enable_and_never_trail_the_drive(tmp_path):
    """The deadlines counted from before the enable: behind by its 0.3 s from the first cycle, a
    loop whose every exchange waits for the drive's next cycle never caught up, and the log said
    every cycle late (a DC-synchronous EtherCAT slave under its own hold: 32 000 of 32 000).
    Skipping whole missed periods then kept a lag of part of one: once the answers came 0.6 ms
    later, every cycle of the busy blocks was late (2 000 of 4 000; 978 on a busy CI machine)."""
    plan = _plan(ServoModel(0.1, 1.0, 0.5, 0.4), 3.0, 0.05)
    drive = SyncPaced("sim://?pace=real&noise=0.01&seed=1" + WINDOW)
    with drive:
        runs = design_excitation(plan.design).runs()
        stream_closed_runs(drive, runs, 1000.0, tmp_path / "log.csv", plan, pace="real", settle_s=0.05)
    log = read_log(tmp_path / "log.csv")
    rows = sum(len(r) for r in log.runs)
    late, missed = int(log.metadata["late_cycles"]), int(log.metadata["missed_cycles"])
    assert log.complete and rows == 4000
    assert late <= missed + 0.01 * rows, (late, missed)  # a stall's cycle, at most
