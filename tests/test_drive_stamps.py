"""Issue 28: a drive has its own clock. A read returns the state latched at the drive's last
tick, stamped with that tick's instant: two reads within one tick repeat the stamp (not an
error, logged as read), a tick may pass unread. Frozen on a drive clock is a stamp standing
still for longer than the watchdog (else 50 ms) of host time; a stamp going back is an error.
The trailer counts ``repeated_samples`` and ``skipped_ticks`` and gives ``drive_tick_s``."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from servobench.bench.log.io import parse_log_text, read_log
from servobench.bench.model.servo import ServoModel
from servobench.bench.procedure.excitation import make_design
from servobench.bench.run.closed import stream_closed_runs
from servobench.bench.run.feedback_check import STAMP_STILL_S, FeedbackCheck
from servobench.bench.run.hold import HoldController, design_hold
from servobench.bench.run.runner import stamp_still_s, stream_runs
from servobench.bench.run.timing_stats import DriveTicks, estimate_tick_s
from servobench.bench.run.travel import ClosedLoopPlan
from servobench.drivers.sim import SimDrive
from servobench.errors import DriveError

PLANT = "M=0.01&B=1&fc_pos=0.5&fc_neg=0.4"
T_S = 1e-3


def tick_steps(n: int, rng: np.random.Generator, repeat: float = 0.10, skip: float = 0.05) -> np.ndarray:
    """Ticks passed between consecutive reads: 0 (a repeat), 2 (one skipped) or 1."""
    r = rng.random(n)
    return np.where(r < repeat, 0, np.where(r < repeat + skip, 2, 1))


def synthetic(tick_s: float, n: int, rng, quantum_s: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Stamps on a tick grid of random phase, quantised like CiA 402 0x1013; and the steps."""
    steps = tick_steps(n - 1, rng)
    index = np.concatenate(([0], np.cumsum(steps)))
    phase = rng.uniform(0.0, 4000.0)
    return np.round((phase + index * tick_s) / quantum_s) * quantum_s, steps


# ----------------------------------------------------------------------------- FeedbackCheck
def test_repeats_and_skips_of_a_drive_clock_pass():
    rng = np.random.default_rng(1)
    stamps, _ = synthetic(T_S, 2000, rng)
    host = np.arange(stamps.size) * T_S  # read every millisecond
    v = np.sin(stamps)
    x = np.cumsum(v)
    for k in range(1, stamps.size):  # a repeated read returns the same latched state
        if stamps[k] == stamps[k - 1]:
            v[k], x[k] = v[k - 1], x[k - 1]
    check = FeedbackCheck(drive_clock=True, dt_s=T_S)
    for k in range(stamps.size):
        check.check(stamps[k], 1.0, v[k], x[k], host[k])
    block = FeedbackCheck(drive_clock=True, dt_s=T_S)
    assert block.first_failure(stamps, np.ones(stamps.size), v, x, host) == stamps.size


def test_a_stamp_standing_still_past_50_ms_of_host_time_is_frozen_feedback():
    check = FeedbackCheck(drive_clock=True, dt_s=T_S)
    assert check.still_s == STAMP_STILL_S == 0.05
    for k in range(5):
        check.check(10.0 + k * T_S, 0.0, 0.0, 0.0, k * T_S)
    stuck = 10.0 + 4 * T_S
    for k in range(5, 54):  # 49 ms of host time on one stamp: repeats
        check.check(stuck, 0.0, 0.0, 0.0, k * T_S)
    with pytest.raises(DriveError) as err:
        check.check(stuck, 0.0, 0.0, 0.0, 0.060)
    message = str(err.value)
    assert message.startswith("feedback frozen: the drive clock stood at") and "\n" not in message
    assert "for 56 ms of host time" in message and "allowed 50 ms" in message
    # the block check stops at the same sample
    t = np.concatenate((10.0 + np.arange(5) * T_S, np.full(60, stuck)))
    host = np.arange(t.size) * T_S
    block = FeedbackCheck(drive_clock=True, dt_s=T_S)
    zeros = np.zeros(t.size)
    stop = block.first_failure(t, zeros, zeros, zeros, host)
    assert stop == 55  # 51 ms after the stamp was first read, at sample 4
    with pytest.raises(DriveError, match="feedback frozen: the drive clock stood"):
        block.check(t[stop], 0.0, 0.0, 0.0, host[stop])


def test_the_drive_watchdog_sets_how_long_a_stamp_may_stand_still():
    check = FeedbackCheck(drive_clock=True, still_s=0.2)
    check.check(1.0, 0.0, 0.0, 0.0, 0.0)
    check.check(1.0, 0.0, 0.0, 0.0, 0.15)
    with pytest.raises(DriveError, match="allowed 200 ms"):
        check.check(1.0, 0.0, 0.0, 0.0, 0.25)


def test_the_runner_takes_the_watchdog_the_drive_url_sets():
    assert stamp_still_s(SimDrive("sim://?watchdog=0.2")) == 0.2
    assert stamp_still_s(SimDrive("sim://")) == STAMP_STILL_S  # not the Drive layer's 0.5 s default


def test_a_drive_clock_going_back_is_an_error():
    check = FeedbackCheck(drive_clock=True)
    check.check(1.000, 0.0, 0.0, 0.0, 0.0)
    check.check(1.001, 0.0, 0.0, 0.0, 0.001)
    with pytest.raises(DriveError) as err:
        check.check(1.0005, 0.0, 0.0, 0.0, 0.002)
    assert str(err.value).startswith("drive clock went backwards: time stamp 1.0005 s after 1.001 s")
    block = FeedbackCheck(drive_clock=True)
    t = np.array([1.0, 1.001, 1.001, 1.0005, 1.002])
    assert block.first_failure(t, np.zeros(5), np.zeros(5), np.zeros(5)) == 3


def test_a_repeated_read_is_not_a_frozen_sensor_but_identical_fresh_samples_still_are():
    """Moving at v = 10: each tick read 5 times (4 repeats, identical feedback) never counts
    towards the frozen cycles; without a drive clock the same rows are frozen feedback."""
    n_ticks, reads = 40, 5
    t = np.repeat(np.arange(n_ticks) * T_S, reads)
    x = np.repeat(np.arange(n_ticks) * T_S, reads)  # moves by one tick of travel per tick
    v = np.full(t.size, 10.0)
    host = np.arange(t.size) * T_S / reads
    stamped = FeedbackCheck(frozen_cycles=4, drive_clock=True, dt_s=T_S)
    for k in range(t.size):
        stamped.check(t[k], 0.0, v[k], x[k], host[k])
    assert FeedbackCheck(4, None, True, T_S).first_failure(t, np.zeros(t.size), v, x, host) == t.size
    plain = FeedbackCheck(frozen_cycles=4, drive_clock=False, dt_s=T_S / reads)
    with pytest.raises(DriveError, match="bit-identical for 4 cycles"):
        for k in range(t.size):
            plain.check(host[k], 0.0, v[k], x[k], host[k])
    # a fresh tick whose feedback is bit-identical to the last still counts
    frozen = np.minimum(x, 9 * T_S)  # the sensor stops at tick 9
    stuck = FeedbackCheck(frozen_cycles=4, drive_clock=True, dt_s=T_S)
    with pytest.raises(DriveError, match="bit-identical for 4 cycles"):
        for k in range(t.size):
            stuck.check(t[k], 0.0, v[k], frozen[k], host[k])
    block = FeedbackCheck(4, None, True, T_S)
    assert block.first_failure(t, np.zeros(t.size), v, frozen, host) == 13 * reads  # 4 ticks on


def test_the_block_check_agrees_with_the_per_sample_check_on_repeated_stamps():
    """Repeats, skips, stamps standing still and going back, frozen stretches: the vectorised
    check stops at the same sample with the same message, however the rows are split."""
    rng = np.random.default_rng(8)
    failures = set()
    for _ in range(60):
        n = int(rng.integers(5, 400))
        steps = tick_steps(n, rng, repeat=0.3)
        if rng.random() < 0.3:  # the drive's clock stops for a while
            k = int(rng.integers(0, n))
            steps[k : k + int(rng.integers(30, 120))] = 0
        if rng.random() < 0.15:
            steps[int(rng.integers(1, n))] = -1
        t = 2.0 + np.cumsum(steps) * T_S
        host = np.cumsum(rng.uniform(0.2e-3, 1.5e-3, n))
        v = np.round(rng.normal(0, 1, n), 1) * (rng.random(n) < 0.7)
        x = np.cumsum(v) * (rng.random(n) < 0.9)
        for k in rng.integers(0, n, 3):  # stretches of frozen feedback
            length = int(rng.integers(1, 40))
            v[k : k + length], x[k : k + length] = v[k], x[k]
        for k in range(1, n):  # a repeated read returns the latched state
            if steps[k] == 0:
                v[k], x[k] = v[k - 1], x[k - 1]
        u = rng.choice([0.0, 1.0, -1.0], n)
        slow, fast = FeedbackCheck(10, 0.5, True, T_S), FeedbackCheck(10, 0.5, True, T_S)
        slow_fail, slow_msg = n, ""
        for k in range(n):
            try:
                slow.check(t[k], u[k], v[k], x[k], host[k])
            except DriveError as err:
                slow_fail, slow_msg = k, str(err)
                break
        fast_fail = n
        cuts = sorted({0, n, *rng.integers(0, n, 2).tolist()})
        for lo, hi in zip(cuts[:-1], cuts[1:], strict=True):
            stop = fast.first_failure(t[lo:hi], u[lo:hi], v[lo:hi], x[lo:hi], host[lo:hi])
            if lo + stop < hi:
                fast_fail = lo + stop
                with pytest.raises(DriveError) as err:
                    fast.check(t[fast_fail], u[fast_fail], v[fast_fail], x[fast_fail], host[fast_fail])
                assert str(err.value) == slow_msg
                break
        assert fast_fail == slow_fail
        failures.add(slow_msg.split(":")[0] + (" stood" if "stood" in slow_msg else ""))
    assert failures >= {"", "drive clock went backwards", "feedback frozen stood", "feedback frozen"}


# ----------------------------------------------------------------------------- the tick
@pytest.mark.parametrize("tick_s", [1e-3, 0.25e-3, 0.125e-3, 1e-3 / 3])
def test_the_tick_is_read_from_stamps_with_repeats_and_skips(tick_s):
    rng = np.random.default_rng(int(tick_s * 1e7))
    n = 5000
    stamps, steps = synthetic(tick_s, n, rng)
    estimate = estimate_tick_s(np.diff(stamps), float(np.abs(stamps).max()))
    if round(tick_s / 1e-6, 6).is_integer():  # a whole number of stamp quanta: exact
        assert estimate == pytest.approx(tick_s, rel=1e-9)
    else:  # within the stamp's quantisation over sqrt(n)
        assert abs(estimate - tick_s) <= 1e-6 / math.sqrt(n)
    ticks = DriveTicks.of([(1, stamps)])
    assert ticks is not None and ticks.tick_s == estimate
    assert ticks.repeated_samples == int(np.count_nonzero(steps == 0))
    assert ticks.skipped_ticks == int(np.count_nonzero(steps == 2))
    assert 0.08 < ticks.repeated_samples / n < 0.12 and 0.03 < ticks.skipped_ticks / n < 0.07


def test_nanosecond_stamps_of_a_large_clock_show_their_tick():
    """EtherCAT DC time: nanoseconds since 2000, some 8e8 s, beyond a double's microsecond."""
    stamps, steps = synthetic(T_S, 3000, np.random.default_rng(3), quantum_s=1e-9)
    stamps = stamps + 8e8
    assert estimate_tick_s(np.diff(stamps), 8e8) == pytest.approx(T_S, rel=1e-6)
    assert DriveTicks.of([(1, stamps)]).skipped_ticks == int(np.count_nonzero(steps == 2))


def test_stamps_off_any_grid_show_no_tick_and_nothing_skipped():
    """A drive that stamps the request instant: steps of the host's jitter, not whole ticks."""
    rng = np.random.default_rng(4)
    jittered = 7.0 + np.cumsum(T_S + rng.normal(0.0, 20e-6, 3000))
    quantised = np.round(jittered / 1e-6) * 1e-6
    fine = 7.0 + np.cumsum(T_S + rng.normal(0.0, 0.3e-6, 3000))
    for stamps in (jittered, quantised, fine):
        assert math.isnan(estimate_tick_s(np.diff(stamps), float(stamps.max())))
        meta = DriveTicks.of([(1, stamps[:1500]), (2, stamps[1500:])]).as_metadata()
        assert "drive_tick_s" not in meta and meta["skipped_ticks"] == 0
        assert meta["repeated_samples"] == 0 and meta["run2_repeated_samples"] == 0
    assert math.isnan(estimate_tick_s(np.array([T_S, T_S])))  # too few steps to tell
    assert DriveTicks.of([(1, np.full(4, math.nan))]) is None


def test_the_log_reader_keeps_equal_instants_and_rejects_decreasing_ones():
    log = parse_log_text("# fs = 1000\nt,u,v\n0,1,2\n0.001,1,2\n0.001,1,2\n0.003,1,3\n")
    assert log.runs[0].t.tolist() == [0.0, 0.001, 0.001, 0.003]
    with pytest.raises(Exception, match="t decreases at the run's sample 3"):
        parse_log_text("# fs = 1000\nt,u,v\n0,1,2\n0.002,1,2\n0.001,1,2\n")
    assert parse_log_text("t,u,v\n0,1,2\n0.002,1,2\n0.002,1,2\n0.004,1,2\n").fs_hz == pytest.approx(500.0)


# ----------------------------------------------------------------------------- streamed
class TickedDrive(SimDrive):
    """The real-time simulated axis whose stamps follow a script of ticks per exchange: 0
    returns the sample of the last tick again (same stamp, same feedback), 2 skips a tick."""

    def __init__(self, url: str, steps: np.ndarray, stop_after: int | None = None) -> None:
        super().__init__(url)
        self.steps = [int(s) for s in steps]
        self.stop_after = stop_after  # the drive's clock stands still from this exchange on
        self.exchanges = 0
        self.tick = 0
        self.last = None

    def _exchange(self, u: float):
        fb = super()._exchange(u)
        k, self.exchanges = self.exchanges, self.exchanges + 1
        step = self.steps[k % len(self.steps)]
        if self.last is not None and (step == 0 or (self.stop_after is not None and k >= self.stop_after)):
            return self.last
        self.tick += step if self.last is not None else 0
        self.last = replace(fb, t_s=123.0 + self.tick * T_S)
        return self.last


def test_a_run_streamed_with_repeated_stamps_logs_every_row_and_counts_them(tmp_path):
    n = 300
    steps = tick_steps(3 * n, np.random.default_rng(5))
    steps[0] = steps[n] = steps[n + 1] = 1  # the first rows and the one settle exchange
    u = 0.8 * np.sign(np.sin(np.arange(n) * 0.05))
    with TickedDrive(f"sim://?clock=real&{PLANT}", steps) as drive:
        res = stream_runs(drive, [(1, u), (2, -u)], 1000.0, tmp_path / "log.csv", settle_s=1e-4)
        assert drive.exchanges == 2 * n + 1  # run 1, one settle cycle, run 2
    log = read_log(tmp_path / "log.csv")
    assert log.complete and res.samples == 2 * n and [len(r) for r in log.runs] == [n, n]
    meta = log.metadata
    assert meta["clock_source"] == "drive"
    run_steps = {1: steps[1:n], 2: steps[n + 2 : 2 * n + 1]}  # the steps into each run's rows
    for run, s in run_steps.items():
        assert int(meta[f"run{run}_repeated_samples"]) == np.count_nonzero(s == 0)
        assert int(meta[f"run{run}_skipped_ticks"]) == np.count_nonzero(s == 2)
        t = log.run(run).t
        assert np.count_nonzero(np.diff(t) == 0) == np.count_nonzero(s == 0)  # logged as read
    both = np.concatenate(list(run_steps.values()))
    assert int(meta["repeated_samples"]) == np.count_nonzero(both == 0) > 0
    assert int(meta["skipped_ticks"]) == np.count_nonzero(both == 2) > 0
    assert float(meta["drive_tick_s"]) == pytest.approx(T_S, rel=1e-9)


def test_a_drive_stamping_each_read_on_its_own_clock_gets_no_tick(tmp_path):
    """The plain real-time simulated axis stamps each sample when it is read: no grid."""
    with SimDrive(f"sim://?clock=real&{PLANT}") as drive:
        stream_runs(drive, [(1, np.full(200, 0.8))], 1000.0, tmp_path / "log.csv")
    meta = read_log(tmp_path / "log.csv").metadata
    assert meta["clock_source"] == "drive" and meta["repeated_samples"] == "0"
    assert "drive_tick_s" not in meta and meta["skipped_ticks"] == "0"


def test_a_drive_clock_standing_still_ends_the_run_and_keeps_the_log(tmp_path):
    steps = np.ones(1000, int)
    with TickedDrive(f"sim://?clock=real&{PLANT}", steps, stop_after=100) as drive:
        with pytest.raises(DriveError) as err:
            stream_runs(drive, [(1, np.full(1000, 0.5))], 1000.0, tmp_path / "log.csv")
        assert not drive.enabled
    assert str(err.value).startswith("feedback frozen: the drive clock stood at 123.099 s for 5")
    log = read_log(tmp_path / "log.csv")
    assert not log.complete and 140 <= len(log.runs[0]) <= 160
    assert int(log.metadata["repeated_samples"]) == len(log.runs[0]) - 100


def test_a_closed_loop_run_counts_the_repeats_too(tmp_path):
    n = 300
    steps = tick_steps(4000, np.random.default_rng(6))
    steps[0] = 1
    model = ServoModel(0.01, 1.0, 0.5, 0.4)
    design = make_design(0.05, period_s=0.2, periods=2, freqs_hz=(5.0, 10.0))
    controller = HoldController(design_hold(model.M, model.B, 20.0), "host", 0.0, 1e-3)
    plan = ClosedLoopPlan(design, controller, 0.05, 0.0, model)
    u_exc = 0.05 * np.sign(np.sin(np.arange(n) * 0.1))
    with TickedDrive(f"sim://?clock=real&{PLANT}&xmin=-0.05&xmax=0.05", steps) as drive:
        stream_closed_runs(drive, [(1, u_exc)], 1000.0, tmp_path / "log.csv", plan, settle_s=0.02)
    log = read_log(tmp_path / "log.csv")
    assert log.complete and len(log.runs[0]) == n and log.metadata["loop"] == "closed"
    repeats = int(np.count_nonzero(np.diff(log.runs[0].t) == 0))
    assert int(log.metadata["repeated_samples"]) == repeats > 0
    assert float(log.metadata["drive_tick_s"]) == pytest.approx(T_S, rel=1e-9)
