"""``sidbe``, ``run`` and ``commission`` name the axis and the time of the run in every log.

The axis is the drive URL's address (limits and plant keys left out), the
time ISO 8601 with an offset, taken when the run starts; a caller's metadata
may name the axis instead (``commission``: its ``[identity]``). ``servobench
fleet`` groups and orders records by them.
"""

from __future__ import annotations

from datetime import datetime, timedelta

import numpy as np

from servobench.bench.cli import main
from servobench.bench.log.identity import configured_axis, parse_time
from servobench.bench.log.io import read_log
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
    for path, axis in ((tmp_path / "run.csv", "sim://?fc_pos=0.4"), (tmp_path / "sidbe" / "log.csv", "sim://")):
        meta = read_log(path).metadata
        assert meta["axis"] == axis  # the plant, without the limits
        assert "+" in meta["time"][19:] or "-" in meta["time"][19:]  # with its UTC offset
        assert _within(meta["time"], before, after)


def test_a_caller_may_name_the_axis(tmp_path):
    with open_drive("sim://") as drive:
        stream_runs(drive, [(1, np.full(50, 1.0))], 1000.0, tmp_path / "l.csv",
                    metadata={"axis": "line 3 / Z"})  # fmt: skip
    assert read_log(tmp_path / "l.csv").metadata["axis"] == "line 3 / Z"


def test_commission_names_the_axis_by_its_configuration(tmp_path):
    config = tmp_path / "bench.toml"
    config.write_text('[identity]\nmachine = "Press 7"\naxis = "Z"\n\n[limits]\nmax_u = 5.0\n'
                      "max_v = 20.0\nxmin = -inf\nxmax = inf\n\n[sidbe]\nperiods = 2\n"
                      "period_s = 0.5\nmax_iterations = 1\n")  # fmt: skip
    before = datetime.now().astimezone()
    out = tmp_path / "rec"
    assert main(["commission", "--drive", "sim://?pace=fast", "--yes", "--config", str(config),
                 "--out", str(out)]) == 0  # fmt: skip
    meta = read_log(out / "log.csv").metadata
    assert meta["axis"] == "Press 7 / Z"
    assert _within(meta["time"], before, datetime.now().astimezone())
    assert configured_axis("", " Z ") == "Z" and configured_axis("Press 7", "") == ""
