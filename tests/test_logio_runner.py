"""Log format round trips, malformed logs, and the runner's never-lose-a-sample guarantee."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from servobench.bench.log.io import LogWriter, parse_log_text, read_log
from servobench.bench.run.runner import LOG_COLUMNS, stream_runs
from servobench.drivers.registry import open_drive
from servobench.errors import DriveFaultError, LogFormatError, UsageError
from servobench.sim_backend.device import PowerState
from servobench.sim_backend.physics.plant import PlantParams, simulate


def square(n: int, amplitude: float, period: int = 200) -> np.ndarray:
    return amplitude * np.where((np.arange(n) // (period // 2)) % 2 == 0, 1.0, -1.0)


def test_round_trip_of_two_runs(tmp_path):
    path = tmp_path / "log.csv"
    with LogWriter(path, {"fs": 1000, "freqs": [1.0, 2.5]}) as w:
        w.append(1, 0.0, 1.5, 0.0, 0.0)
        w.append(1, 0.001, 1.5, 0.01, 0.0)
        w.append_block(
            np.full(3, 2), np.arange(3) * 1e-3, np.full(3, -1.0), np.arange(3.0), np.zeros(3)
        )
    log = read_log(path)
    assert log.complete and log.fs_hz == 1000.0 and log.metadata["freqs"] == "1,2.5"
    assert [r.run for r in log.runs] == [1, 2]
    assert_allclose(log.run(2).v, [0.0, 1.0, 2.0])
    assert log.run(1).u.tolist() == [1.5, 1.5]


def test_columns_in_any_order_and_extra_columns():
    log = parse_log_text("# fs = 100\nx,u,t,extra\n0,1,0,9\n0.1,1,0.01,9\n")
    run = log.runs[0]
    assert run.run == 1 and run.v is None and run.extra["extra"].tolist() == [9.0, 9.0]


def test_truncated_last_row_is_dropped_and_marks_incomplete():
    log = parse_log_text("# fs = 10\nt,u,v\n0,1,0\n0.1,1,0.5\n0.2,1,0.")
    assert len(log.runs[0]) == 2 and not log.complete


def test_sample_rate_inferred_from_time():
    log = parse_log_text("t,u,v\n0,1,0\n0.002,1,0\n0.004,1,0\n")
    assert log.fs_hz == pytest.approx(500.0)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("", "no CSV header"),
        ("# fs = 1\n", "no CSV header"),
        ("t,u\n0,1\n", "v or an x"),
        ("t,v\n0,1\n", "lacks column"),
        ("t,u,v\n", "no data rows"),
        ("t,u,v\n0,1\n", "expected 3 fields"),
        ("t,u,v\n0,one,2\n", "malformed number"),
        ("t,u,v\n0,1,nan\n", "non-finite"),
        ("t,u,v,v\n0,1,2,3\n", "repeated column"),
        ("t,u,v\n0,1,2\n0,1,2\n", "not increasing"),
        ("run,t,u,v\n1.5,0,1,2\n", "integers"),
        ("# fs = fast\nt,u,v\n0,1,2\n", "fs"),
        ("t,u,v\n0,1,2\n", "sample rate"),
        ("# fs = 1\nt,u,v\n0,1,2\n0.1,1\x0b,2\n", "4: control character"),
        ("# fs = 1\rt,u,v\r0,1,2\r0.1,\u20281,2\r", "4: control character"),
    ],
)
def test_malformed_logs_raise_one_clear_error(text, match):
    with pytest.raises(LogFormatError, match=match):
        parse_log_text(text)


def test_missing_and_binary_files(tmp_path):
    with pytest.raises(LogFormatError, match="no such log"):
        read_log(tmp_path / "nope.csv")
    (tmp_path / "bin.csv").write_bytes(b"\xff\xfe\x00\x01")
    with pytest.raises(LogFormatError, match="UTF-8"):
        read_log(tmp_path / "bin.csv")
    (tmp_path / "bad.mat").write_bytes(b"not a mat file")
    with pytest.raises(LogFormatError, match="MATLAB"):
        read_log(tmp_path / "bad.mat")


def test_mat_files_with_a_variable_mapping(tmp_path):
    from scipy.io import savemat

    t = np.arange(5) * 1e-3
    savemat(tmp_path / "d.mat", {"time": t, "volt": np.ones(5), "gain": 2.0, "pos": t * 3})
    log = read_log(tmp_path / "d.mat", "t=time,u=volt*gain,x=pos")
    assert_allclose(log.runs[0].u, 2.0)
    assert log.fs_hz == pytest.approx(1000.0)
    with pytest.raises(LogFormatError, match="no variable"):
        read_log(tmp_path / "d.mat", "t=time,u=amps,x=pos")
    with pytest.raises(LogFormatError, match="mapping lacks"):
        read_log(tmp_path / "d.mat")


@pytest.mark.parametrize("pace", ["fast", "real"])
def test_runner_logs_every_sample_of_both_runs(tmp_path, pace):
    u1 = square(400, 3.0)
    path = tmp_path / "log.csv"
    with open_drive("sim://?M=0.1&B=1") as drive:
        result = stream_runs(drive, [(1, u1), (2, 0.9 * u1)], 1000.0, path, pace=pace, settle_s=0.3)
        assert drive.device.state is PowerState.DISABLED
    log = read_log(path)
    assert result.complete and log.complete and result.samples == 800
    assert [len(r) for r in log.runs] == [400, 400]
    assert_allclose(log.run(1).u, u1)
    v_expected, _ = simulate(u1, 1000.0, PlantParams(M=0.1, B=1.0))
    assert_allclose(log.run(1).v, v_expected, atol=1e-9)
    assert_allclose(np.diff(log.run(2).t), 1e-3, rtol=1e-6)
    assert "run1_host_jitter_std_s" in log.metadata
    assert read_log(path).runs[0].extra["t_host"].shape == (400,)
    for key, unit in drive.log_metadata().items():  # the drive's own lines reach the header
        assert log.metadata[key] == unit
    assert {"unit_u", "unit_v", "unit_x"} <= set(log.metadata)


def test_runner_rejects_zero_sample_rate(tmp_path):
    with open_drive("sim://") as drive, pytest.raises(UsageError, match="sample rate"):
        stream_runs(drive, [(1, np.ones(3))], 0.0, tmp_path / "l.csv")


def test_fault_mid_run_keeps_every_sample_and_marks_incomplete(tmp_path):
    path = tmp_path / "log.csv"
    u = square(1000, 3.0)

    class Trip:
        def __init__(self, drive):
            self.drive = drive

        def __call__(self, done, total):
            if done >= 300:
                self.drive.device.fault(0x5441, "over-temperature")

    with open_drive("sim://") as drive:
        with pytest.raises(DriveFaultError, match="0x5441"):
            stream_runs(drive, [(1, u)], 1000.0, path, pace="real", progress=Trip(drive))
        assert drive.device.command == 0.0 and not drive.enabled
    log = read_log(path)
    assert not log.complete
    assert 300 <= len(log.runs[0]) < 1000
    assert "over-temperature" in log.metadata["reason"]
    assert_allclose(log.runs[0].u, u[: len(log.runs[0])])


def test_ctrl_c_stops_the_axis_and_keeps_the_log(tmp_path):
    path = tmp_path / "log.csv"

    def interrupt(done, total):
        if done >= 200:
            raise KeyboardInterrupt

    with open_drive("sim://") as drive:
        with pytest.raises(KeyboardInterrupt):
            stream_runs(drive, [(1, square(1000, 3.0))], 1000.0, path, pace="real", progress=interrupt)
        assert drive.device.state is PowerState.DISABLED
    log = read_log(path)
    assert not log.complete and log.metadata["reason"].startswith("interrupted")
    assert len(log.runs[0]) >= 200
    assert list(LOG_COLUMNS[:5]) == ["run", "t", "u", "v", "x"]


def test_limit_breach_in_block_mode_keeps_the_samples_before_it(tmp_path):
    path = tmp_path / "log.csv"
    u = np.full(5000, 3.0)
    with open_drive("sim://?max_v=1.5") as drive:
        from servobench.errors import LimitExceededError

        with pytest.raises(LimitExceededError, match="velocity"):
            stream_runs(drive, [(1, u)], 1000.0, path, pace="fast")
        assert drive.device.state is PowerState.DISABLED
    log = read_log(path)
    assert not log.complete
    v_expected, _ = simulate(u, 1000.0, PlantParams())
    breach = int(np.flatnonzero(v_expected > 1.5)[0])
    assert len(log.runs[0]) == breach + 1
    assert_allclose(log.runs[0].v, v_expected[: breach + 1], atol=1e-9)
