"""What the terminal says (issue 24, defect 7): units where they exist, a set-up warning once per
session, a lost link as one line that names the drive and the state of the axis."""

from __future__ import annotations

import json
import re
import threading

import pytest

from servobench.bench import cli
from servobench.bench.cli import main
from servobench.bench.testing.served import ServedSim

WATCHDOG_WORDS = "feeds the drive's watchdog with any request"


def test_list_maps_shows_the_units_of_each_map(capsys):
    assert main(["list", "maps"]) == 0
    out = capsys.readouterr().out
    assert "u [], v [], x []" not in out
    lines = out.splitlines()
    sim = lines.index("  servobench-sim")
    assert lines[sim + 2].strip() == "u [N m], v [rad/s], x [rad]"
    zlac = lines.index("  zlac8015d")
    assert lines[zlac + 2].strip() == "u [A], v [rad/s], x [inc]"


def test_the_modbus_watchdog_warning_is_said_once_per_session(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(cli, "session_file", lambda: tmp_path / "said")
    # the host runs inside the test's worker: a watchdog with room for a loaded test machine (a
    # fresh-clone suite once saw the default 0.5 s trip after the first sample); this test is
    # about the warning, which any armed watchdog gives
    patient = "&pace=fast&watchdog=2"
    with ServedSim("modbus-tcp") as served:
        for i in range(2):
            assert main(["run", "--drive", served.url + patient, "--out", str(tmp_path / f"{i}.csv"),
                         "--periods", "2", "--period", "0.5"]) == 0  # fmt: skip
        err = capsys.readouterr().err
    assert err.count(WATCHDOG_WORDS) == 1, err
    # another session hears it again
    monkeypatch.setattr(cli, "session_file", lambda: tmp_path / "said-by-another-session")
    with ServedSim("modbus-tcp") as served:
        assert main(["run", "--drive", served.url + patient, "--out", str(tmp_path / "2.csv"),
                     "--periods", "2", "--period", "0.5"]) == 0  # fmt: skip
    assert capsys.readouterr().err.count(WATCHDOG_WORDS) == 1


@pytest.mark.slow
def test_a_lost_link_is_one_line_naming_the_drive_and_the_state_of_the_axis(tmp_path, capsys):
    served = ServedSim("modbus-tcp")
    url = served.start()
    killer = threading.Timer(1.5, served.proc.kill)  # the drive's power fails mid-run
    killer.start()
    try:
        rc = main(["run", "--drive", url, "--out", str(tmp_path / "lost.csv"), "--periods", "4"])
    finally:
        killer.cancel()
        served.stop()
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("servobench: error")]
    assert rc == 1 and len(err) == 1, err
    where = url.split("?")[0].split("//")[1]  # host:port, named by the Drive layer or the driver
    assert where in err[0] and "lost" in err[0]
    assert "watchdog" in err[0] and "stops it within 0.5 s" in err[0]
    assert "partial log kept" in err[0]
    assert not err[0].startswith("servobench: error: Connection reset by peer")


def test_a_refused_dry_run_leaves_nothing_and_the_retry_works(tmp_path, capsys, monkeypatch):
    import io

    config = tmp_path / "bench.toml"
    config.write_text("[limits]\nmax_u = 5.0\nmax_v = 20.0\nxmin = -inf\nxmax = inf\n")
    out = tmp_path / "rec"
    monkeypatch.setattr("sys.stdin", io.StringIO(""))  # no terminal, and no --yes
    args = ["commission", "--drive", "sim://?pace=fast", "--config", str(config), "--dry-run", "--out", str(out)]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "the limits must be confirmed" in err and f"nothing was written to {out}" in err
    assert not out.exists()
    out.mkdir()  # a folder the user made: kept, and still empty
    assert main(args) == 1 and list(out.iterdir()) == []
    capsys.readouterr()
    assert main([*args, "--yes"]) == 0  # the retry into the same folder
    assert json.loads((out / "commission.json").read_text())["status"] == "dry-run"
    assert main([*args, "--yes"]) == 0  # a dry run's status file alone is no record
    capsys.readouterr()


def test_commission_terminal_lines_carry_units(tmp_path, capsys):
    config = tmp_path / "bench.toml"
    config.write_text("[limits]\nmax_u = 5.0\nmax_v = 20.0\nxmin = -inf\nxmax = inf\n\n"
                      "[sidbe]\nperiods = 3\nperiod_s = 1.0\n")  # fmt: skip
    out = tmp_path / "rec"
    rc = main(["commission", "--drive", "sim://?pace=fast&noise=0.002&seed=4", "--config", str(config),
               "--yes", "--out", str(out)])  # fmt: skip
    lines = [" ".join(line.split()) for line in capsys.readouterr().out.splitlines() if line.strip()]
    assert rc == 0, lines[-3:]

    def line(start: str) -> str:
        return next(x for x in lines if x.startswith(start))

    assert re.fullmatch(r"ok feedback: velocity \S+ rad/s, position \S+ rad", line("ok feedback:"))
    assert "|u| <= 5 N m, |v| <= 20 rad/s, x in [-inf, inf] rad" in line("ok limits")
    assert " N m), positive command" in line("ok moves both ways")
    assert line("ok M = ").count("N m") >= 2 and "kg m^2" in line("ok M = ")
    ff = line("ok friction feed-forward:")
    assert ff.endswith("N m, viscous " + ff.split("viscous ")[1].split()[0] + " N m s/rad")
    pi = line("ok velocity PI:")
    assert "N m s/rad, Ki" in pi and "N m/rad (crossover" in pi
    assert "rad/s without" in line("ok simulated tracking error") and lines[-1].startswith("PASS")
    assert json.loads((out / "commission.json").read_text())["verdict"] in ("pass", "pass with remarks")
