"""Loops that choose each command from the last sample run on the cyclic engine's terms (issue 22).

The relay probe and the commissioning bump test used their own loops: the
nominal grid ``k dt`` as the instant of a sample the drive did not stamp, log
writing on the cyclic path, no real-time footing and no timing in the log.
On :class:`~servobench.bench.run.reactive.ReactiveCycle` they take the
runner's: absolute deadlines, each sample's best instant with ``t_unc``, the
``# clock_source`` and ``# rt_*`` lines and the cycle's timing in the trailer.
"""

from __future__ import annotations

import numpy as np
import pytest

from servobench.bench.commission.bump import run_bump_test
from servobench.bench.commission.config import BumpSettings
from servobench.bench.commission.limits import ConfirmedLimits
from servobench.bench.log.io import read_log
from servobench.bench.run.probe import run_probe
from servobench.bench.run.reactive import ReactiveCycle
from servobench.bench.run.travel import TravelWindow
from servobench.bench.testing.served import PATIENT_KEYS, ServedSim
from servobench.drivers.registry import open_drive
from servobench.drivers.sim import SimDrive

PLANT = "M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"
CYCLE_KEYS = ("host_jitter_p50_s", "host_jitter_p99_s", "host_jitter_max_s", "missed_cycles", "t_unc_p99_s")


def test_a_served_drive_without_a_stamp_is_bump_tested_on_host_brackets(tmp_path):
    """Modbus TCP without the time-stamp register, in real time: the bump test's log says
    where its instants come from, brackets each sample and carries the cycle's timing."""
    args = ["--clock", "real", "--no-timestamp"]
    limits = ConfirmedLimits(5.0, 20.0, -100.0, 100.0)
    with ServedSim("modbus-tcp", f"sim://?{PLANT}", args) as served, open_drive(
        served.url + PATIENT_KEYS["modbus-tcp"]
    ) as drive:
        result = run_bump_test(drive, limits, BumpSettings(fs_hz=200.0), tmp_path / "bump.csv", pace="real")
    assert result.breakaway_pos > 0 and result.breakaway_neg > 0
    log = read_log(tmp_path / "bump.csv")
    assert log.complete and log.metadata["clock_source"] == "host" and log.metadata["pace"] == "real"
    assert log.metadata["rt_gc"] == "frozen/disabled" and "rt_policy" in log.metadata
    for key in CYCLE_KEYS:
        assert key in log.metadata
    t_unc = np.concatenate([r.extra["t_unc"] for r in log.runs])
    assert np.all(t_unc > 0) and float(log.metadata["t_unc_p99_s"]) > 0
    t = np.concatenate([r.t for r in log.runs])
    assert np.all(np.diff(t) > 0)
    # the host's brackets, not the nominal grid: the intervals scatter around 5 ms
    assert np.std(np.diff(t)) > 0 and abs(np.median(np.diff(t)) - 5e-3) < 1e-3


def test_the_relay_probe_takes_a_stamping_drive_s_instants(tmp_path):
    """An in-process drive that moves in wall-clock time and stamps its samples: the probe's
    log is in the drive's time (t_unc 0), its deadlines are kept, and the relay still learns
    the axis."""
    with SimDrive(f"sim://?clock=real&{PLANT}&xmin=-1&xmax=1") as drive:
        result = run_probe(drive, TravelWindow(-1.0, 1.0), 500.0, 0.5, 4.0, tmp_path / "probe.csv")
    log = read_log(tmp_path / "probe.csv")
    assert log.complete and log.metadata["clock_source"] == "drive"
    assert all(np.all(r.extra["t_unc"] == 0) for r in log.runs)
    assert int(log.metadata["missed_cycles"]) < 0.05 * sum(len(r) for r in log.runs)
    m = result.model
    assert abs(m.M / 0.1 - 1) < 0.3 and abs(m.B - 1) < 0.3


def test_a_lock_step_drive_streamed_fast_stays_on_the_nominal_grid(tmp_path):
    with SimDrive(f"sim://?{PLANT}") as drive, ReactiveCycle(
        drive, 0.002, "fast", tmp_path / "x.csv", {"fs": 500}
    ) as cycle:
        drive.set_cycle(0.002)
        drive.enable()
        ts = [cycle.exchange(1, 1.0)[2] for _ in range(50)]
        drive.disable()
        cycle.finish("complete")
    log = read_log(tmp_path / "x.csv")
    np.testing.assert_allclose(log.runs[0].t, np.arange(50) * 0.002, atol=1e-12)
    np.testing.assert_allclose(ts, np.arange(50) * 0.002, atol=1e-12)
    assert "clock_source" not in log.metadata and "t_unc" not in log.runs[0].extra


def test_an_error_mid_loop_leaves_the_log_incomplete_with_its_rows(tmp_path):
    with SimDrive(f"sim://?clock=real&{PLANT}") as drive:
        with pytest.raises(RuntimeError, match="boom"), ReactiveCycle(
            drive, 0.002, "real", tmp_path / "x.csv", {"fs": 500}
        ) as cycle:
            drive.enable()
            for _ in range(20):
                cycle.exchange(1, 0.0)
            raise RuntimeError("boom")
        drive.disable()
    log = read_log(tmp_path / "x.csv")
    assert not log.complete and log.metadata["reason"] == "boom" and len(log.runs[0]) == 20
