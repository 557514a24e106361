"""``sidbe`` and ``run`` name the axis and the time of the run in every log they write.

The axis is the drive URL's address (limits and plant keys left out), the
time ISO 8601 with an offset, taken when the run starts; a caller's metadata
may name the axis instead. ``servobench fleet`` groups and orders records by them.
"""

from __future__ import annotations

from datetime import datetime, timedelta

import numpy as np

from servobench.bench.cli import main
from servobench.bench.logidentity import parse_time
from servobench.bench.logio import read_log
from servobench.bench.run.runner import stream_runs
from servobench.drivers.registry import open_drive


def _within(text: str, before: datetime, after: datetime) -> bool:
    when = parse_time(text)
    return before - timedelta(seconds=1) <= when <= after + timedelta(seconds=1)


def test_run_and_sidbe_logs_name_their_axis_and_time(tmp_path):
    before = datetime.now().astimezone()
    assert main(["run", "--drive", "sim://?max_u=5&fc_pos=0.4", "--out", str(tmp_path / "run.csv"),
                 "--periods", "2", "--period", "0.5"]) == 0  # fmt: skip
    assert main(["sidbe", "--drive", "sim://?max_u=5", "--out", str(tmp_path / "sidbe"), "--periods",
                 "2", "--period", "0.5", "--max-iterations", "1", "--no-plots", "--json"]) == 0  # fmt: skip
    after = datetime.now().astimezone()
    for path in (tmp_path / "run.csv", tmp_path / "sidbe" / "log.csv"):
        meta = read_log(path).metadata
        assert meta["axis"] == "sim://"
        assert "+" in meta["time"][19:] or "-" in meta["time"][19:]  # with its UTC offset
        assert _within(meta["time"], before, after)


def test_a_caller_may_name_the_axis(tmp_path):
    with open_drive("sim://") as drive:
        stream_runs(drive, [(1, np.full(50, 1.0))], 1000.0, tmp_path / "l.csv",
                    metadata={"axis": "line 3 / Z"})  # fmt: skip
    assert read_log(tmp_path / "l.csv").metadata["axis"] == "line 3 / Z"
