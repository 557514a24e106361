"""Run folders and early ends keep the user's data: refused reruns, explained logs, named partial logs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

import servobench.drivers.registry
from servobench.bench.cli import main
from servobench.bench.logio import read_log
from servobench.bench.testing.fault_scenarios import SIM_URL
from servobench.bench.testing.served import ServedSim
from servobench.drivers.sim import SimDrive
from servobench.sim_backend.device import PowerState

REPO = Path(__file__).resolve().parents[1]
SHORT = ["--periods", "2", "--period", "0.5", "--no-plots"]
CONFIG = """
[limits]
max_u = 5.0
max_v = 20.0
xmin = -inf
xmax = inf

[sidbe]
periods = 3
period_s = 1.0
"""


class DiesMidRun(SimDrive):
    """The link drops once the excitation is under way (the third block of cycles)."""

    blocks = 0

    def _exchange_block(self, u):
        self.blocks += 1
        if self.blocks > 2:
            raise ConnectionResetError(104, "Connection reset by peer")
        return super()._exchange_block(u)


class CtrlCMidRun(DiesMidRun):
    def _exchange_block(self, u):
        self.blocks += 1
        if self.blocks > 2:
            raise KeyboardInterrupt
        return SimDrive._exchange_block(self, u)


@pytest.fixture
def drive_class(monkeypatch):
    """Make every drive the command opens an instance of the class the test sets."""
    chosen: dict[str, type] = {}
    made: list[SimDrive] = []

    def factory(url):
        drive = chosen["cls"](url)
        made.append(drive)
        return drive

    monkeypatch.setattr(servobench.drivers.registry, "open_drive", factory)

    def use(cls):
        chosen["cls"] = cls
        return made

    return use


def partial_log_of(line: str) -> Path:
    """The path the one-line error names as the partial log."""
    assert "partial log kept: " in line, line
    return Path(line.split("partial log kept: ")[1].split(" (")[0])


def test_sidbe_refuses_a_folder_holding_a_run_before_touching_the_drive(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    for name in ("log.csv", "log-2.csv", "model.json"):
        (out / name).write_text(f"earlier {name}\n")
    rc = main(["sidbe", "--drive", "nosuch://x", "--out", str(out), *SHORT])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and len(err) == 1
    assert "already holds a run (log-2.csv, log.csv, model.json)" in err[0] and "nosuch" not in err[0]
    assert all((out / n).read_text() == f"earlier {n}\n" for n in ("log.csv", "log-2.csv", "model.json"))


def test_model_json_explains_log_csv_against_log_n(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()  # an empty folder is fine
    args = ["sidbe", "--drive", "sim://?noise=0.02&seed=1", "--out", str(out), "--fit-threshold", "99.99",
            "--max-iterations", "2", "--json", *SHORT]  # fmt: skip
    assert main(args) == 0
    model = json.loads(capsys.readouterr().out)
    files = model["files"]
    assert set(files) == {p.name for p in out.glob("*.csv")} == {"log.csv", "log-1.csv", "log-2.csv"}
    source = files["log.csv"].split()[2].rstrip(":")
    assert (out / "log.csv").read_bytes() == (out / source).read_bytes()
    assert files["log-2.csv"].startswith("round 2, amplitude 2:")
    readme = (REPO / "README.md").read_text()
    assert "log-N.csv" in readme and "servobench-runs/" in (REPO / ".gitignore").read_text()


@pytest.mark.parametrize("command", ["sidbe", "run"])
def test_a_drive_that_dies_names_the_partial_log(command, tmp_path, capsys, drive_class):
    made = drive_class(DiesMidRun)
    out = tmp_path / ("run" if command == "sidbe" else "log.csv")
    args = [command, "--drive", "sim://?pace=fast", "--out", str(out), "--json", "--periods", "4"]
    assert main(args) == 1
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()[-1]
    assert err.startswith("servobench: error: Connection reset by peer; partial log kept: ")
    log = partial_log_of(err)
    assert log == (out / "log-1.csv" if command == "sidbe" else out)
    partial = read_log(log)
    assert not partial.complete and "Connection reset" in partial.metadata["reason"]
    assert json.loads(captured.out) == {"error": err.removeprefix("servobench: error: ")}
    assert made[-1].device.state is PowerState.DISABLED


def test_ctrl_c_names_the_partial_log(tmp_path, capsys, drive_class):
    drive_class(CtrlCMidRun)
    out = tmp_path / "run"
    assert main(["sidbe", "--drive", "sim://?pace=fast", "--out", str(out), "--periods", "4"]) == 130
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert line.startswith("servobench: interrupted; axis stopped; partial log kept: ")
    assert partial_log_of(line) == out / "log-1.csv"
    assert read_log(out / "log-1.csv").metadata["reason"] == "interrupted (Ctrl-C)"


def test_commission_names_the_partial_log_and_the_record(tmp_path, capsys, drive_class):
    drive_class(DiesMidRun)
    config = tmp_path / "bench.toml"
    config.write_text(CONFIG)
    out = tmp_path / "record"
    rc = main(["commission", "--drive", "sim://?pace=fast", "--yes", "--config", str(config), "--out", str(out)])
    assert rc == 1
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert "Connection reset by peer" in line and f"the record so far is kept in {out}" in line
    assert not read_log(partial_log_of(line)).complete


def test_a_served_drive_that_faults_names_the_partial_log(tmp_path):
    """Through a real transport and the installed command: ``sidbe`` against ``serve-sim --fault``."""
    out = tmp_path / "run"
    with ServedSim("modbus-tcp", SIM_URL, ["--fault", "exception@300:4"], clock="lockstep") as served:
        proc = subprocess.run(
            [sys.executable, "-m", "servobench", "sidbe", "--drive", served.url + "&pace=fast",
             "--out", str(out), "--amplitude", "1", *SHORT],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    last = proc.stderr.splitlines()[-1]
    assert "Modbus exception 4" in last and partial_log_of(last) == out / "log-1.csv"
    assert len(read_log(out / "log-1.csv").runs[0]) == 299
