"""Long runs in bounded memory: the log is streamed, timing statistics are O(1).

10^6 samples go through ``sim://`` (fast, block exchange) here; the same
through a served CANopen drive takes minutes (about 0.4 ms per sample across
the process boundary) and is measured by ``benchmarks/faults.py``.
"""

from __future__ import annotations

import threading
import time
import tracemalloc
from pathlib import Path

import numpy as np
import psutil
import pytest

from servobench.bench.run.runner import FeedbackCheck, PeriodStats, stream_runs
from servobench.drivers.registry import open_drive
from servobench.errors import DriveError
from servobench.sim_backend.physics.plant import PlantParams, simulate

SIM = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"
PARAMS = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)
#: Growth of the resident set allowed while streaming 10^6 samples [bytes]
#: (the per-run arrays this replaced took 16 MB, 32 MB at their peak).
RSS_BUDGET = 8e6


def square(n: int, half: int = 500) -> np.ndarray:
    return np.where((np.arange(n) // half) % 2 == 0, 1.0, -1.0)


class PeakRSS(threading.Thread):
    """Samples this process's resident set every 5 ms until stopped."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.proc = psutil.Process()
        self.peak = self.proc.memory_info().rss
        self._stop_event = threading.Event()

    def run(self) -> None:
        while not self._stop_event.wait(0.005):
            self.peak = max(self.peak, self.proc.memory_info().rss)

    def stop(self) -> int:
        self._stop_event.set()
        self.join()
        return max(self.peak, self.proc.memory_info().rss)


def tail(path: Path, size: int = 4096) -> list[str]:
    with open(path, "rb") as fh:
        fh.seek(0, 2)
        fh.seek(max(0, fh.tell() - size))
        return fh.read().decode().splitlines()


def test_a_million_samples_stream_in_bounded_memory(tmp_path: Path) -> None:
    n = 1_000_000
    u = square(n)
    path = tmp_path / "long.csv"
    with open_drive(SIM) as drive:
        base = psutil.Process().memory_info().rss
        watch = PeakRSS()
        watch.start()
        t0 = time.perf_counter()
        result = stream_runs(drive, [(1, u)], 1000.0, path)
        seconds = time.perf_counter() - t0
        growth = watch.stop() - base
    assert result.complete and result.samples == n
    assert growth < RSS_BUDGET, f"resident set grew {growth / 1e6:.1f} MB for 10^6 samples"
    lines = tail(path)
    assert "# status = complete" in lines and f"# samples = {n}" in lines
    last = next(line for line in reversed(lines) if not line.startswith("#")).split(",")
    v_ref, x_ref = simulate(u, 1000.0, PARAMS)  # the last sample equals the lock-step plant's
    assert float(last[3]) == pytest.approx(v_ref[-1], rel=1e-9, abs=1e-12)
    assert float(last[4]) == pytest.approx(x_ref[-1], rel=1e-9)
    assert path.stat().st_size > 30e6  # every sample is on disk
    print(f"10^6 samples via sim:// in {seconds:.2f} s, RSS +{growth / 1e6:.2f} MB")


@pytest.mark.parametrize("block", [False, True], ids=["per-sample", "blocks"])
def test_memory_does_not_grow_with_the_run(tmp_path: Path, block: bool) -> None:
    """Peak Python allocations while streaming are the same for 3x the samples."""
    peaks = []
    for n in (5_000, 15_000):
        with open_drive(SIM) as drive:
            drive.supports_block = block
            u = square(n, 250)
            tracemalloc.start()
            stream_runs(drive, [(1, u)], 1000.0, tmp_path / f"{n}.csv")
            peaks.append(tracemalloc.get_traced_memory()[1])
            tracemalloc.stop()
    # holding arrays of n floats (the old timing arrays) would add 2 * 8 * 10000 = 160 kB
    assert peaks[1] < peaks[0] + 64_000, peaks


def test_streamed_period_statistics_equal_numpy() -> None:
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.5e-3, 1.5e-3, 5001))
    one, blocks = PeriodStats(), PeriodStats()
    for tk in t:
        one.add(float(tk))
    for chunk in np.array_split(t, [1, 7, 2000, 2001, 4500]):
        blocks.add_block(chunk)
    d = np.diff(t)
    for stats in (one, blocks):
        assert stats.samples == t.size
        assert stats.mean == pytest.approx(d.mean(), rel=1e-12)
        assert stats.std == pytest.approx(d.std(), rel=1e-9)
        assert stats.max == d.max()
    assert np.isnan(PeriodStats().mean)


def test_block_check_agrees_with_the_per_sample_check() -> None:
    """The vectorised feedback check stops at the same sample with the same message."""
    rng = np.random.default_rng(4)
    failures = 0
    for _ in range(40):
        n = int(rng.integers(5, 400))
        v = np.round(rng.normal(0, 1, n), 1) * (rng.random(n) < 0.7)
        x = np.cumsum(v) * (rng.random(n) < 0.9)
        for k in rng.integers(0, n, 3):  # stretches of frozen feedback
            length = int(rng.integers(1, 40))
            v[k : k + length], x[k : k + length] = v[k], x[k]
        if rng.random() < 0.2:
            v[rng.integers(0, n)] = np.nan
        t = np.arange(n) * 1e-3
        u = rng.choice([0.0, 1.0, -1.0], n)
        cut = rng.integers(0, n)
        slow, fast = FeedbackCheck(10, 0.5, True, 0.2), FeedbackCheck(10, 0.5, True, 0.2)
        slow_fail = fast_fail = n
        slow_msg = ""
        for k in range(n):
            try:
                slow.check(t[k], u[k], v[k], x[k])
            except DriveError as err:
                slow_fail, slow_msg = k, str(err)
                break
        for lo, hi in ((0, cut), (cut, n)):
            stop = fast.first_failure(t[lo:hi], u[lo:hi], v[lo:hi], x[lo:hi])
            if lo + stop < hi:
                fast_fail = lo + stop
                with pytest.raises(DriveError) as err:
                    fast.check(t[fast_fail], u[fast_fail], v[fast_fail], x[fast_fail])
                assert str(err.value) == slow_msg
                break
        assert fast_fail == slow_fail
        failures += slow_fail < n
    assert failures >= 10  # frozen stretches and NaNs were caught, not just clean blocks
