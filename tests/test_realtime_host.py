"""The real-time host (issue 22, parts 2-4): OS footing, the log ring, instants and their
uncertainty, timing-weighted identification and the timing figure."""

from __future__ import annotations

import gc
import io
import json
import math
import os
import sys
import time
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np
import pytest

from servobench.bench.identify.auto import identify
from servobench.bench.identify.dataset import prepare
from servobench.bench.identify.joint import identify_joint, pair_regression
from servobench.bench.log.io import LogWriter, read_log
from servobench.bench.procedure.sidbe import SidbeOptions, run_sidbe
from servobench.bench.report.summary import print_result
from servobench.bench.run.ring_writer import RingLogWriter
from servobench.bench.run.runner import LOG_COLUMNS, REALTIME_COLUMNS, stream_runs
from servobench.bench.run.timing_stats import CycleClock, CycleTiming
from servobench.drivers.base import Feedback
from servobench.drivers.sim import SimDrive
from servobench.errors import DriveError
from servobench.realtime import realtime_thread
from servobench.verdict import Verdict, exit_status

PLANT = "M=0.01&B=1&fc_pos=0.5&fc_neg=0.4"


class NoStampDrive(SimDrive):
    """The real-time simulated axis without a time stamp: the host must bracket its instants."""

    drive_clock = False


class SlowAnsweringDrive(NoStampDrive):
    """Answers each exchange 5-20 ms late, at random: timing made bad on purpose."""

    def __init__(self, url) -> None:
        super().__init__(url)
        self.rng = np.random.default_rng(7)

    def _exchange(self, u: float) -> Feedback:
        time.sleep(self.rng.uniform(0.005, 0.020))
        return super()._exchange(u)


class FailingDrive(NoStampDrive):
    """Fails at its ``fail_at``-th exchange."""

    fail_at = 150

    def __init__(self, url) -> None:
        super().__init__(url)
        self.count = 0

    def _exchange(self, u: float) -> Feedback:
        self.count += 1
        if self.count == self.fail_at:
            raise DriveError("link lost on purpose")
        return super()._exchange(u)


def square(n: int, half: int, amplitude: float) -> np.ndarray:
    return amplitude * np.where((np.arange(n) // half) % 2 == 0, 1.0, -1.0)


# ------------------------------------------------------------------ OS footing
def test_realtime_thread_reports_what_it_got_and_reverts_everything():
    before = (os.sched_getscheduler(0), os.sched_getaffinity(0), gc.isenabled(), sys.getswitchinterval())
    with realtime_thread() as grant:
        meta = grant.as_metadata()
        assert set(meta) >= {"rt_policy", "rt_affinity", "rt_memory_locked", "rt_gc", "rt_switchinterval_s"}
        assert not gc.isenabled() and meta["rt_gc"] == "frozen/disabled"
        assert sys.getswitchinterval() < before[3]
        if grant.fifo:
            assert os.sched_getscheduler(0) == os.SCHED_FIFO
        else:  # refused: the reason is stated, never assumed
            assert "refused" in grant.policy
        if meta["rt_affinity"].isdigit():
            assert os.sched_getaffinity(0) == {int(meta["rt_affinity"])}
        assert meta["rt_memory_locked"] == "yes" or meta["rt_memory_locked"].startswith("no (")
    after = (os.sched_getscheduler(0), os.sched_getaffinity(0), gc.isenabled(), sys.getswitchinterval())
    assert after == before


def test_the_other_threads_cannot_be_preempted_while_they_hold_the_gil_and_get_their_policy_back():
    import threading

    stop = threading.Event()
    other = threading.Thread(target=stop.wait)
    other.start()
    try:
        with realtime_thread() as grant:
            inside = os.sched_getscheduler(other.native_id)
        after = os.sched_getscheduler(other.native_id)
    finally:
        stop.set()
        other.join()
    if grant.fifo:
        assert inside == os.SCHED_FIFO and grant.other_threads.endswith("SCHED_FIFO 1")
    assert after == os.SCHED_OTHER


def test_the_real_time_footing_can_be_turned_off_and_the_log_says_so(monkeypatch, tmp_path):
    monkeypatch.setenv("SERVOBENCH_REALTIME", "off")
    with realtime_thread() as grant:
        assert os.sched_getscheduler(0) != os.SCHED_FIFO and gc.isenabled()
    assert "turned off" in grant.policy
    with SimDrive(f"sim://?clock=real&{PLANT}") as drive:
        stream_runs(drive, [(1, square(50, 10, 1.0))], 1000.0, tmp_path / "log.csv")
    assert "SERVOBENCH_REALTIME" in read_log(tmp_path / "log.csv").metadata["rt_policy"]


def test_realtime_thread_reverts_on_an_error():
    before = (os.sched_getscheduler(0), os.sched_getaffinity(0), gc.isenabled())
    with pytest.raises(RuntimeError), realtime_thread():
        raise RuntimeError("boom")
    assert (os.sched_getscheduler(0), os.sched_getaffinity(0), gc.isenabled()) == before


# ------------------------------------------------------------------ the ring
def test_ring_rows_reach_the_file_while_streaming_in_order(tmp_path):
    path = tmp_path / "ring.csv"
    writer = LogWriter(path, {"fs": 1000}, ("run", "t", "u", "v", "x"))
    ring = RingLogWriter(writer, capacity=16, flush_s=0.002)
    for k in range(100):  # many times the ring: the cyclic side waits, never drops
        ring.append(1, k * 1e-3, 0.5, float(k), 0.0)
    time.sleep(0.1)
    text = path.read_text()  # written as they arrive: before close, before the trailer
    assert text.count("\n1,") == 100
    ring.close()
    writer.finish("complete", samples=writer.rows)
    log = read_log(path)
    np.testing.assert_array_equal(log.runs[0].v, np.arange(100.0))
    assert log.complete


def test_cycle_timing_counts_missed_slots_and_late_requests():
    clock = CycleClock(6)
    starts = [0.0, 0.001, 0.002, 0.005, 0.006, 0.0071]  # slots 3 and 4 missed
    for k, s in enumerate(starts):
        clock.mark(k, k * 0.001, s, s + 1e-4, 5e-5)
    c = CycleTiming.of([clock], 1e-3)
    assert c.missed_cycles == 2
    assert c.late_cycles == 3  # deadlines k ms: the last three started 2 ms late
    clock2 = CycleClock(3)
    for k, s in enumerate([0.0, 0.003, 0.004]):
        clock2.mark(k, k * 0.001, s, s, 0.0)
    assert CycleTiming.of([clock2], 1e-3).late_cycles == 2
    assert c.jitter_max_s == pytest.approx(0.002)
    assert c.t_unc_p99_s == pytest.approx(5e-5)


# ------------------------------------------------------------------ the runner
def test_real_pace_with_a_drive_time_stamp_logs_the_drive_clock_and_the_footing(tmp_path):
    u = square(600, 50, 2.0)
    with SimDrive(f"sim://?clock=real&{PLANT}") as drive:
        res = stream_runs(drive, [(1, u), (2, 0.5 * u)], 1000.0, tmp_path / "log.csv", settle_s=0.05)
    log = read_log(tmp_path / "log.csv")
    assert res.clock_source == log.metadata["clock_source"] == "drive"
    assert tuple(log.metadata[k] for k in ("rt_gc",)) == ("frozen/disabled",)
    assert log.metadata["rt_policy"].startswith(("SCHED_FIFO", "SCHED_OTHER"))
    header = (tmp_path / "log.csv").read_text().split("\n")
    assert next(line for line in header if line.startswith("run,")) == ",".join(REALTIME_COLUMNS)
    assert REALTIME_COLUMNS[: len(LOG_COLUMNS)] == LOG_COLUMNS  # old columns first, in order
    for key in ("host_jitter_p50_s", "host_jitter_p99_s", "host_jitter_max_s", "missed_cycles",
                "run1_host_jitter_p99_s", "t_unc_p99_s"):  # fmt: skip
        assert key in log.metadata
    assert np.all(log.runs[0].extra["t_unc"] == 0.0)
    assert res.cycle_timing.cycles == 1200
    # an exact drive clock makes an exact model, however the host's cycle went
    result = identify(log, "joint")
    assert pytest.approx(0.01, rel=1e-6) == result.model.M
    assert result.model.coulomb_neg == pytest.approx(0.4, rel=1e-6)
    # exact instants: no timing share, only the exact fit's own (vanishing) statistical sigma
    assert result.timing.clock_source == "drive" and result.timing.model_error_max_pct < 1e-6
    assert result.timing.to_json()["delay_s"] == pytest.approx(0.0, abs=1e-9)


def test_real_pace_without_a_time_stamp_brackets_each_exchange(tmp_path):
    u = square(400, 50, 2.0)
    with NoStampDrive(f"sim://?clock=real&{PLANT}") as drive:
        res = stream_runs(drive, [(1, u)], 1000.0, tmp_path / "log.csv")
    log = read_log(tmp_path / "log.csv")
    assert res.clock_source == log.metadata["clock_source"] == "host"
    run = log.runs[0]
    t_unc, t_host = run.extra["t_unc"], run.extra["t_host"]
    assert np.all(t_unc > 0) and np.all(np.diff(run.t) > 0)
    # t is the bracket's midpoint: the answer came t_unc after it (same origin up to the first bracket)
    lag = (t_host - t_host[0]) - (run.t - run.t[0])
    np.testing.assert_allclose(lag, t_unc - t_unc[0], atol=1e-8)


def test_an_error_mid_run_still_writes_every_sample_and_the_trailer(tmp_path):
    u = square(400, 50, 1.0)
    with FailingDrive(f"sim://?clock=real&{PLANT}") as drive, pytest.raises(DriveError):
        stream_runs(drive, [(1, u)], 1000.0, tmp_path / "log.csv")
    log = read_log(tmp_path / "log.csv")
    assert not log.complete
    assert log.metadata["reason"] == "link lost on purpose"
    assert len(log.runs[0]) == FailingDrive.fail_at - 1
    assert int(log.metadata["samples"]) == FailingDrive.fail_at - 1
    assert "host_jitter_p99_s" in log.metadata


def test_fast_pace_keeps_the_lock_step_log_as_before(tmp_path):
    u = square(300, 50, 1.0)
    with SimDrive(f"sim://?{PLANT}") as drive:
        res = stream_runs(drive, [(1, u)], 1000.0, tmp_path / "log.csv")
    log = read_log(tmp_path / "log.csv")
    assert res.cycle_timing is None and "clock_source" not in log.metadata
    assert "t_unc" not in log.runs[0].extra
    np.testing.assert_allclose(log.runs[0].t, np.arange(300) * 1e-3, rtol=0, atol=1e-12)


# ---------------------------------------------------------- identification
def _host_clock_log(tmp_path: Path, half_width_s: float) -> Path:
    """A real-time drive-stamped log rewritten as a host-bracketed one: each logged instant
    is off its true one by up to its half-width ``t_unc``."""
    u = square(2000, 100, 2.0)
    with SimDrive(f"sim://?clock=real&{PLANT}") as drive:
        stream_runs(drive, [(1, u), (2, 0.5 * u)], 1000.0, tmp_path / "stamped.csv", settle_s=0.05)
    log = read_log(tmp_path / "stamped.csv")
    rng = np.random.default_rng(3)
    path = tmp_path / "host.csv"
    meta = {**log.metadata, "clock_source": "host", "status": "running"}
    writer = LogWriter(path, meta, REALTIME_COLUMNS)
    for r in log.runs:
        # the bracket [t - a, t + b] of each true instant t, never reaching a neighbour's
        gap = np.diff(r.t)
        room_before = np.concatenate(([half_width_s], 0.45 * gap))
        room_after = np.concatenate((0.45 * gap, [half_width_s]))
        a = rng.uniform(0.0, 1.0, len(r)) * np.minimum(half_width_s, room_before)
        b = rng.uniform(0.0, 1.0, len(r)) * np.minimum(half_width_s, room_after)
        t, half = r.t + 0.5 * (b - a), 0.5 * (a + b)
        writer.append_block(np.full(len(r), r.run), t, r.u, r.v, r.x, r.extra["t_host"], half)
    writer.finish("complete")
    return path


def test_weighting_by_timing_uncertainty_beats_ignoring_it(tmp_path):
    log = read_log(_host_clock_log(tmp_path, 4e-4))
    plain_runs = tuple(
        type(r)(r.run, r.t, r.u, r.v, r.x, {k: v for k, v in r.extra.items() if k != "t_unc"})
        for r in log.runs
    )
    plain_log = type(log)(plain_runs, log.metadata, log.fs_hz)

    def worst(m) -> float:
        return max(abs(m.M / 0.01 - 1), abs(m.B - 1), abs(m.coulomb_pos / 0.5 - 1), abs(m.coulomb_neg / 0.4 - 1))

    # the pair regression, where the weights act: well below the unweighted error
    weighted = identify_joint(prepare(log), refine_oe=False).model
    plain = identify_joint(prepare(plain_log), refine_oe=False).model
    assert worst(weighted) < 0.6 * worst(plain)
    # and the whole estimator within the idle target
    assert worst(identify(log, "joint").model) < 0.003


def test_a_slow_cycle_of_a_fast_plant_with_wide_brackets_keeps_its_inertia(tmp_path):
    """Modbus RTU without a time stamp: 50 Hz, a 10 ms time constant, every command reversal
    crossing zero velocity, each instant bracketed 2.4 ms wide although the drive sampled at
    a steady point of the bracket (+-0.1 ms). The timing weights leave the transient pairs --
    the ones that carry M -- next to no weight, so the pair regression's vanishing residual
    must not end the estimate there, nor may the weights take the exact repeats of a drive's
    1e-6 velocity steps for a noise-free sensor (together they gave M -58 % on served runs)."""
    from servobench.bench.identify.simulation import simulate_velocity
    from servobench.bench.model.servo import ServoModel

    rng = np.random.default_rng(22)
    fs, n = 50.0, 400
    true = ServoModel(0.01, 1.0, 0.5, 0.4)
    path = tmp_path / "rtu.csv"
    meta = {"fs": "50", "clock_source": "host", "pace": "real", "status": "running"}
    writer = LogWriter(path, meta, REALTIME_COLUMNS)
    for run, amp in ((1, 1.0), (2, 0.9)):
        u = np.where((np.arange(n) // 8) % 2 == 0, amp, -amp) * np.where(np.arange(n) % 48 < 24, 1.0, -1.0)
        dt = 1 / fs + rng.uniform(-3e-4, 3e-4, n - 1)  # the drive sampled when each request came
        t_true = np.concatenate(([0.0], np.cumsum(dt)))
        v = simulate_velocity(true, u, dt, 0.0)
        half = 1.2e-3 + rng.uniform(-1e-4, 1e-4, n)
        t_log = t_true + 4e-4 + rng.uniform(-1e-4, 1e-4, n)  # a steady point of a wide bracket
        x = np.concatenate(([0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * dt)))
        writer.append_block(np.full(n, run), t_log, u, np.round(v, 6), np.round(x, 6), t_log, half)
    writer.finish("complete")
    log = read_log(path)
    result = identify(log, "joint")
    # the pair regression alone (its weights assume no less noise than the 1e-6 step), and all of it
    for model in (pair_regression(prepare(log)), result.model):
        for got, want in ((model.M, 0.01), (model.B, 1.0), (model.coulomb_pos, 0.5), (model.coulomb_neg, 0.4)):
            assert got == pytest.approx(want, rel=0.01)
    # the timing figure reads the instants' real scatter (uniform +-0.1 ms: 0.058 ms), not the
    # 1.2 ms brackets, and predicts an error within the stated accuracy, as measured
    timing = result.timing
    assert timing.instant_scatter_s == pytest.approx(1e-4 / math.sqrt(3.0), rel=0.35)
    assert timing.within_accuracy and 0 < timing.model_error_max_pct < 1.0
    assert result.to_json()["timing"]["instant_scatter_s"] == pytest.approx(timing.instant_scatter_s)


def test_timing_figure_predicts_an_error_that_grows_with_the_uncertainty(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    small = identify(read_log(_host_clock_log(tmp_path / "a", 2e-5)), "joint")
    large = identify(read_log(_host_clock_log(tmp_path / "b", 4e-4)), "joint")
    assert small.timing.clock_source == "host"
    assert 0 < small.timing.model_error_max_pct < large.timing.model_error_max_pct
    js = large.to_json()
    assert js["clock_source"] == "host"
    assert set(js["timing"]) >= {"jitter_p50_s", "jitter_p99_s", "jitter_max_s", "missed_cycles",
                                 "model_error_pct", "model_error_max_pct", "within_accuracy"}  # fmt: skip
    # the bound "within accuracy" is judged by: the 1-sigma prediction at the figure's coverage
    assert js["timing"]["coverage_sigma"] == 2.0
    assert js["timing"]["model_error_bound_pct"] == pytest.approx(2.0 * js["timing"]["model_error_max_pct"])
    assert js["timing"]["within_accuracy"] == (js["timing"]["model_error_bound_pct"] <= 1.0)
    json.dumps(js, allow_nan=False)


def test_within_accuracy_means_within_it_at_two_sigma():
    """The stated accuracy is claimed at two sigma: a fresh-clone suite's served Modbus RTU run
    (0.25 ms tick, host stalls of 37 ms) predicted 0.65 % for M, 1 sigma, said "within accuracy",
    and was 1.15 % off. Now 0.65 % is outside the stated 1 %, and the first line gives 1.3 %."""
    from servobench.bench.identify.timing import TimingFigure

    def figure(m_pct: float) -> TimingFigure:
        return TimingFigure("host", {"missed_cycles": 0.0}, 50.0,
                            {"M": m_pct, "B": 0.09, "coulomb_pos": 0.08, "coulomb_neg": 0.13},
                            time_constant_s=0.01)  # fmt: skip

    assert figure(0.5).within_accuracy and not figure(0.5).warning_lines()
    late = figure(0.65)
    assert not late.within_accuracy and late.to_json()["within_accuracy"] is False
    assert "M may be off by 1.3 % (2 sigma" in late.warning_lines()[0]


def test_a_run_with_bad_timing_says_so_in_its_first_lines(tmp_path):
    drive = SlowAnsweringDrive(f"sim://?clock=real&{PLANT}")
    options = SidbeOptions(fs_hz=100.0, period_s=1.0, periods=2, max_iterations=1, plots=False, method="joint")
    result = run_sidbe(drive, options, tmp_path / "out")
    timing = result.result.timing
    assert timing.clock_source == "host" and not timing.within_accuracy
    out = io.StringIO()
    with redirect_stdout(out):
        print_result(result.result)
    first, second = out.getvalue().splitlines()[:2]
    assert first.startswith("WARNING: timing takes the model outside its stated accuracy")
    assert "clock_source = host" in first
    assert "--fs" in second and "free a core" in second and "time-stamps" in second
    saved = json.loads((tmp_path / "out" / "model.json").read_text())
    assert saved["timing"]["within_accuracy"] is False and saved["timing"]["advice"]
    assert math.isfinite(saved["timing"]["jitter_max_s"]) and saved["timing"]["missed_cycles"] > 0
    # the model fits its log, yet the verdict is no plain pass: the parameters may be off by more
    # than stated (a stalled host once gave M 45 % off under a 98.3 % fit and a PASS); exit 0
    assert result.passed and result.verdict is Verdict.REMARKS and exit_status(result.verdict) == 0
    assert saved["verdict"] == result.to_json()["verdict"] == "pass with remarks"
    headline = result.headline()
    assert headline.startswith("PASS with remarks: SIDBE verification fit") and "\n" not in headline
    assert f"off by up to {timing.model_error_bound_pct:.2g} %" in headline and "WARNING below" in headline


def test_a_run_whose_timing_is_within_accuracy_passes_plainly(tmp_path):
    result = run_sidbe(SimDrive(f"sim://?{PLANT}"), SidbeOptions(period_s=1.0, periods=2, max_iterations=1,
                       plots=False), tmp_path / "out")  # fmt: skip
    assert result.result.timing is None or result.result.timing.within_accuracy
    assert result.verdict is Verdict.PASS and result.to_json()["verdict"] == "pass"
    assert result.headline().startswith("PASS: SIDBE verification fit")


# ---------------------------------------------------------- kernel-timed SYNC
def test_kernel_sync_names_the_sync_of_each_answer_and_counts_late_rpdos_and_missed_syncs():
    from types import SimpleNamespace

    from servobench.drivers.canopen.cycle import MAX_FRAME_BITS, CycleIO, sync_index

    assert sync_index(100.0032, 100.0, 1e-3) == 3
    io = CycleIO(SimpleNamespace(bitrate=1_000_000, sync_cob=0x80), None, None)
    io.period_s, io._sync0_wall_s, io._wall_minus_host_s, io._last_index = 1e-3, 100.0, 50.0, -1
    io._rx_wall_s = 100.0032  # the answer to SYNC 3
    t_host, unc, t_sync = io._kernel_instant(100.0022 - 50.0)  # RPDO 0.2 ms after SYNC 2: in time
    assert t_host == pytest.approx(100.003 - 50.0) and t_sync == pytest.approx(0.003)
    assert unc == pytest.approx(MAX_FRAME_BITS / 1e6)
    assert io.counts == {"late_rpdos": 0, "missed_syncs": 0}
    io._rx_wall_s = 100.0062  # SYNC 6: slots 4 and 5 went unanswered
    io._kernel_instant(100.0058 - 50.0)  # RPDO 0.8 ms after SYNC 5: after the window
    assert io.counts == {"late_rpdos": 1, "missed_syncs": 2}


def test_the_kernel_sync_is_python_cans_periodic_send():
    from types import SimpleNamespace

    import can

    from servobench.drivers.canopen.cycle import CycleIO

    with can.Bus(interface="virtual", channel="rt-sync") as host, \
            can.Bus(interface="virtual", channel="rt-sync") as drive:  # fmt: skip
        io = CycleIO(SimpleNamespace(bitrate=1_000_000, sync_cob=0x80), SimpleNamespace(bus=host), None)
        io.start_kernel_sync(0.005)
        assert io.kernel_sync
        time.sleep(0.2)
        io.stop_kernel_sync()
        frames = []
        while (msg := drive.recv(0.0)) is not None:
            frames.append(msg)
        assert not io.kernel_sync
    assert len(frames) >= 10 and all(m.arbitration_id == 0x80 and not m.data for m in frames)


# ---------------------------------------------------------- command lead
class LeadingDrive(SimDrive):
    """Latches the command 1 ms before it samples, as the ODrive ASCII protocol's torque line
    reaches a free-running drive before the feedback query does. Both at pinned instants of the
    device's clock, so a loaded host's preemption cannot lengthen the lead past LEAD_S."""

    LEAD_S = 1e-3

    def command_lead_s(self) -> float:
        return self.LEAD_S

    def _exchange(self, u: float) -> Feedback:
        latched = time.monotonic()  # the device's clock
        with self.device.instant(latched):
            self.device.set_command(u)
        sampled = latched + self.LEAD_S
        while time.monotonic() < sampled:
            pass
        with self.device.instant(sampled):  # exactly LEAD_S on, however late this thread ran
            s = self.device.sample()
        return Feedback(s.t_s, s.velocity, s.position)


def test_a_command_that_leads_its_sample_is_identified_as_a_negative_delay(tmp_path):
    rng = np.random.default_rng(5)
    u = np.repeat(rng.choice([-3.0, -2.0, -1.0, 1.0, 2.0, 3.0], 60), 10)  # 600 samples at 200 Hz
    with LeadingDrive(f"sim://?clock=real&{PLANT}") as drive:
        stream_runs(drive, [(1, u)], 200.0, tmp_path / "log.csv")
    log = read_log(tmp_path / "log.csv")
    assert float(log.metadata["command_lead_s"]) == LeadingDrive.LEAD_S

    def worst(m) -> float:
        return max(abs(m.M / 0.01 - 1), abs(m.B - 1), abs(m.coulomb_pos / 0.5 - 1), abs(m.coulomb_neg / 0.4 - 1))

    moved = identify(log, "joint")
    ignored = identify(type(log)(log.runs, {k: v for k, v in log.metadata.items() if k != "command_lead_s"},
                                 log.fs_hz), "joint")  # fmt: skip
    assert worst(ignored.model) > 0.05  # a delay >= 0 cannot take a command that acts early
    assert worst(moved.model) < 0.005  # the delay free from -command_lead_s on
    assert moved.model.delay_s == pytest.approx(-LeadingDrive.LEAD_S, abs=0.05e-3)
    assert any("command_lead_s" in note for note in moved.notes)
