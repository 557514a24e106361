"""Closed-loop excitation at the rate the drive's link carries, with the achieved rate logged.

As in open loop (issue 10 §4): without ``--fs`` the rate follows
:meth:`Drive.max_rate_hz` (a ``sim://`` drive declaring the limit of a Modbus
RTU link at 115200 baud, 137 cycles/s: 100 Hz), an ``--fs`` beyond it is
refused, and the rate the host achieved goes into the log trailer
(``fs_achieved``), the JSON of ``run`` and ``sidbe``, and the summary.
"""

from __future__ import annotations

import json
import re

import pytest

import servobench.drivers.registry
from servobench.bench.cli import main
from servobench.bench.log.io import read_log
from servobench.drivers.sim import SimDrive

URL = "sim://?noise=0.01&seed=1&xmin=-0.5&xmax=0.5&pace=fast"


class OverRtu(SimDrive):
    def max_rate_hz(self) -> float:
        return 137.0


@pytest.fixture(autouse=True)
def over_rtu(monkeypatch):
    monkeypatch.setattr(servobench.drivers.registry, "open_drive", OverRtu)


def test_run_in_closed_loop_at_the_link_rate_logs_what_it_achieved(tmp_path, capsys):
    out = tmp_path / "log.csv"
    rc = main(["run", "--drive", URL, "--loop", "closed", "--periods", "2", "--period", "2",
               "--out", str(out), "--json"])  # fmt: skip
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    got = json.loads(captured.out)
    log = read_log(out)
    assert log.metadata["loop"] == "closed" and float(log.metadata["fs"]) == 100.0
    achieved = float(log.metadata["fs_achieved"])
    assert got["fs_achieved"] == pytest.approx(achieved, rel=1e-4)
    assert achieved > 100.0  # pace=fast: as fast as the host goes
    assert all(len(r) == 400 for r in log.runs)


def test_sidbe_in_closed_loop_reports_the_achieved_rate(tmp_path, capsys):
    out = tmp_path / "run"
    args = ["sidbe", "--drive", URL, "--loop", "closed", "--periods", "3",
            "--period", "2", "--max-iterations", "1", "--no-plots", "--out", str(out)]  # fmt: skip
    assert main([*args, "--json"]) == 0
    model = json.loads(capsys.readouterr().out)
    log = read_log(out / "log.csv")
    assert model["loop"] == "closed" and model["fs"] == 100.0
    assert model["fs_achieved"] == pytest.approx(float(log.metadata["fs_achieved"]), rel=1e-4)
    assert main([*args[:-1], str(tmp_path / "again")]) == 0
    summary = " ".join(capsys.readouterr().out.replace("\u2502", " ").split())  # the table's cells
    # lock-step (pace=fast): the rate is the drive's clock; the streaming speed is no axis rate
    assert re.search(r"cycle rate 100 Hz on the drive's clock \(lock-step, pace=fast: streamed [\d.e+]+x "
                     r"faster than real time; the link carries 137 Hz\)", summary)  # fmt: skip
    assert "Hz achieved" not in summary


def test_an_fs_beyond_the_link_is_refused_in_closed_loop_too(tmp_path, capsys):
    rc = main(["run", "--drive", URL, "--loop", "closed", "--fs", "500", "--out", str(tmp_path / "l.csv")])
    err = capsys.readouterr().err
    assert rc == 1 and "--fs 500 Hz is beyond the sim:// link: it carries at most 137 cycles/s" in err
    assert not (tmp_path / "l.csv").exists()
