"""``servobench commission`` end to end on ``sim://``: the record, every refusal, --dry-run, Ctrl-C."""

from __future__ import annotations

import json
import math
from html.parser import HTMLParser
from pathlib import Path

import pytest
from test_commission_bump import StuckFault

import servobench.drivers.registry
from servobench.bench.cli import main
from servobench.bench.log.io import read_log
from servobench.drivers.sim import SimDrive
from servobench.sim_backend.device import PowerState

PLANT = {"M": 0.1, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}
#: Limits for --yes, and a short SIDBE (3 periods of 1 s per run): noise-free, it is exact and fast.
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
#: identify --json keys every model.json must carry
IDENTIFY_KEYS = {"M", "B", "pole", "dc_gain", "coulomb_pos", "coulomb_neg", "fit_percent", "method"}


@pytest.fixture
def config(tmp_path) -> Path:
    path = tmp_path / "bench.toml"
    path.write_text(CONFIG)
    return path


@pytest.fixture
def drives(monkeypatch):
    """Every drive the command creates, in order; ``drives.cls`` picks the SimDrive subclass."""
    made: list[SimDrive] = []
    real = servobench.drivers.registry.open_drive

    class Made(list):
        cls = None

    made = Made()

    def factory(url):
        drive = made.cls(url) if made.cls is not None else real(url)
        made.append(drive)
        return drive

    monkeypatch.setattr(servobench.drivers.registry, "open_drive", factory)
    return made


class _Page(HTMLParser):
    def __init__(self):
        super().__init__()
        self.images: list[str] = []
        self.external: list[str] = []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.images.append(a.get("src", ""))
        if tag == "script" or (tag == "link" and a.get("href")):
            self.external.append(tag)
        if tag in ("img", "iframe") and not a.get("src", "").startswith("data:"):
            self.external.append(a.get("src", ""))


def check_record(out: Path, plant=PLANT) -> dict:
    """The commissioning record is complete and matches the plant within 1 %."""
    model = json.loads((out / "model.json").read_text())
    assert set(model) >= IDENTIFY_KEYS
    pole, gain = -plant["B"] / plant["M"], 1 / plant["B"]
    assert model["pole"] == pytest.approx(pole, rel=0.01)
    assert model["dc_gain"] == pytest.approx(gain, rel=0.01)
    assert set(model["std"]) >= {"M", "B", "coulomb_pos", "coulomb_neg", "pole", "dc_gain"}
    ff, pi = model["feed_forward"], model["velocity_pi"]
    assert ff["coulomb_pos"] == pytest.approx(model["coulomb_pos"]) and ff["viscous"] == pytest.approx(model["B"])
    assert pi["kp"] > 0 and pi["phase_margin_deg"] >= 59.0
    check = model["simulation_check"]
    assert check["rms_error_with_ff"] < check["rms_error_without_ff"]

    page = _Page()
    page.feed((out / "report.html").read_text())
    pngs = [s for s in page.images if s.startswith("data:image/png;base64,")]
    assert len(pngs) >= 7 and len(pngs) == len(page.images)  # bump, excitation, velocity, FRF, friction, compensation, ...
    assert model["identity"]["transport"] == model["commissioning"]["drive"]["transport"]
    assert page.external == []
    html = (out / "report.html").read_text()
    for heading in ("Summary", "Values to program into the drive", "Evidence"):
        assert f"<h2>{heading}</h2>" in html
    for heading in ("Excitation", "Velocities", "Frequency response", "Friction-velocity map", "Diagnosis",
                    "Friction compensation and velocity-loop PI"):  # fmt: skip
        assert f"<h3>{heading}" in html

    from scipy.io import loadmat

    mat = loadmat(str(out / "commission.mat"))
    assert {"t", "u", "v", "x", "run", "M", "B", "coulomb_pos", "pi_kp", "ff_coulomb_pos"} <= set(mat)
    assert float(mat["B"].squeeze()) == pytest.approx(model["B"])
    log = read_log(out / "log.csv")
    assert log.complete and mat["t"].size == sum(len(r) for r in log.runs)
    assert read_log(out / "commission.mat").runs[0].u.size == log.runs[0].u.size

    status = json.loads((out / "commission.json").read_text())
    assert status["status"] == "complete" and "report.html" in status["files"]
    return model


def test_end_to_end_on_sim(tmp_path, config, drives, capsys):
    out = tmp_path / "rec"
    rc = main(["commission", "--drive", "sim://?pace=fast", "--yes", "--config", str(config),
               "--out", str(out), "--record-bus", str(tmp_path / "bus.log")])  # fmt: skip
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    model = check_record(out)
    assert model["units"]["B"] == "N m s/rad" and model["units"]["coulomb_pos"] == "N m"  # sim:// is rotary SI
    diag = model["commissioning"]["diagnose"]  # with the diagnosis' verdict (issue 12)
    assert diag["verdict"] in ("explained", "unexplained") and diag["noise_floor_percent"] > 0
    assert f"verdict: {diag['verdict']} -- " in (out / "report.html").read_text()
    assert "cannot record bus traffic" in captured.out and "continuing without" in captured.out
    assert len(drives) == 2  # read-only check, then the connection with the limits
    assert drives[1].limits.max_command == 5.0 and drives[1].limits.max_velocity == 20.0
    assert drives[1].device.state is PowerState.DISABLED and not drives[1].is_open


def test_limits_missing_under_yes_refuse_before_connecting(tmp_path, drives, capsys):
    cfg = tmp_path / "partial.toml"
    cfg.write_text("[limits]\nmax_u = 5.0\n")
    rc = main(["commission", "--drive", "sim://?pace=fast", "--yes", "--config", str(cfg), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 1
    assert err.startswith("servobench: error: --yes needs every limit, missing: max_v, xmin, xmax")
    assert err.count("\n") == 1
    assert drives == []
    assert json.loads((tmp_path / "o" / "commission.json").read_text())["status"] == "refused"


def test_without_a_terminal_and_without_yes_refuses(tmp_path, config, drives, capsys):
    rc = main(["commission", "--drive", "sim://?pace=fast", "--config", str(config), "--out", str(tmp_path / "o")])
    assert rc == 1
    assert "limits must be confirmed" in capsys.readouterr().err
    assert all(d.device.sample().t_s == 0.0 for d in drives)  # nothing was clocked


def test_fault_that_will_not_reset_refuses(tmp_path, config, drives, capsys):
    drives.cls = StuckFault
    rc = main(["commission", "--drive", "sim://?pace=fast", "--yes", "--config", str(config), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 1 and "fault 0x2310 that will not reset" in err
    assert len(drives) == 1
    assert drives[0].device.state is PowerState.FAULT and drives[0].device.command == 0.0
    assert not drives[0].is_open


def test_no_motion_refuses_with_the_axis_disabled(tmp_path, config, drives, capsys):
    out = tmp_path / "o"
    rc = main(["commission", "--drive", "sim://?pace=fast&fc_pos=50&fc_neg=50", "--yes", "--config", str(config),
               "--out", str(out)])  # fmt: skip
    err = capsys.readouterr().err
    assert rc == 1 and "no motion in the bump test" in err
    assert drives[-1].device.state is PowerState.DISABLED and drives[-1].device.command == 0.0
    assert read_log(out / "bump.csv").complete
    assert not (out / "log.csv").exists()
    status = json.loads((out / "commission.json").read_text())
    assert status["status"] == "refused" and status["steps_done"] == ["check", "limits"]


class Counting(SimDrive):
    enables = 0
    commands = 0

    def _enable(self):
        type(self).enables += 1
        super()._enable()

    def _write_command(self, u):
        type(self).commands += 1
        super()._write_command(u)

    def _exchange(self, u):
        type(self).commands += 1
        return super()._exchange(u)


def test_dry_run_moves_nothing_and_says_what_it_would_do(tmp_path, config, drives, capsys):
    drives.cls = Counting
    out = tmp_path / "o"
    rc = main(["commission", "--drive", "sim://?pace=fast", "--yes", "--dry-run", "--config", str(config), "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0
    assert Counting.enables == 0 and Counting.commands == 0
    assert all(d.device.sample().t_s == 0.0 and d.device.sample().position == 0.0 for d in drives)
    assert "would run SIDBE" in text and "bump test" in text and "would reconnect as sim://" in text
    assert sorted(p.name for p in out.iterdir()) == ["commission.json"]
    assert json.loads((out / "commission.json").read_text())["status"] == "dry-run"


class InterruptInSidbe(SimDrive):
    """Ctrl-C once the SIDBE excitation is under way (the bump test streams per cycle, SIDBE in blocks)."""

    blocks = 0

    def _exchange_block(self, u):
        self.blocks += 1
        if self.blocks > 2:
            raise KeyboardInterrupt
        return super()._exchange_block(u)


def test_ctrl_c_leaves_the_axis_disabled_and_keeps_the_partial_log(tmp_path, config, drives, capsys):
    drives.cls = InterruptInSidbe
    out = tmp_path / "o"
    rc = main(["commission", "--drive", "sim://?pace=fast", "--yes", "--config", str(config), "--out", str(out)])
    assert rc == 130
    assert "interrupted" in capsys.readouterr().err
    drive = drives[-1]
    assert drive.device.state is PowerState.DISABLED and drive.device.command == 0.0 and not drive.is_open
    assert read_log(out / "bump.csv").complete
    status = json.loads((out / "commission.json").read_text())
    assert status["status"] == "interrupted" and "bump" in status["steps_done"]
    logs = [p for p in out.glob("*.csv") if p.name != "bump.csv"]
    assert logs, "the partial SIDBE log is kept"
    partial = read_log(logs[0])
    assert not partial.complete and "Ctrl-C" in partial.metadata.get("reason", "")


def test_existing_record_is_not_overwritten(tmp_path, config, capsys):
    out = tmp_path / "o"
    out.mkdir()
    (out / "commission.json").write_text("{}")
    rc = main(["commission", "--drive", "sim://?pace=fast", "--yes", "--config", str(config), "--out", str(out)])
    assert rc == 1 and "already holds a commissioning record" in capsys.readouterr().err
    assert math.isfinite(len((out / "commission.json").read_text()))


def test_unknown_sidbe_option_refuses_before_moving(tmp_path, drives, capsys):
    cfg = tmp_path / "bench.toml"
    cfg.write_text(CONFIG + "amplitud = 1.0\n")
    out = tmp_path / "o"
    rc = main(["commission", "--drive", "sim://?pace=fast", "--yes", "--config", str(cfg), "--out", str(out)])
    assert rc == 1 and "[sidbe] has unknown key(s) amplitud" in capsys.readouterr().err
    assert not (out / "bump.csv").exists()
    assert all(d.device.sample().t_s == 0.0 for d in drives)


def test_interactive_confirmation_at_the_terminal(tmp_path, drives):
    import io

    from rich.console import Console as RichConsole

    from servobench.bench.commission.config import load_config
    from servobench.bench.commission.limits import TerminalPrompter
    from servobench.bench.commission.sequence import CommissionOptions, commission
    from servobench.bench.commission.ui import Console

    console = Console(RichConsole(file=io.StringIO(), width=200))
    answers = io.StringIO("2.5\n\n-1\n1\ny\n")  # max_v: the configured 20 is the default
    cfg = tmp_path / "bench.toml"
    cfg.write_text("[limits]\nmax_v = 20.0\n")
    options = CommissionOptions("sim://?pace=fast", load_config(cfg), tmp_path / "o", dry_run=True)
    result = commission(options, console, TerminalPrompter(console.rich, answers))
    assert result.status == "dry-run"
    status = json.loads((tmp_path / "o" / "commission.json").read_text())
    assert status["limits"] == {"max_u": 2.5, "max_v": 20.0, "xmin": -1.0, "xmax": 1.0}
    assert any("would reconnect as sim://?pace=fast&max_u=2.5&max_v=20.0&xmin=-1.0&xmax=1.0" in line
               for line in console.lines)  # fmt: skip


def test_leaving_the_envelope_during_sidbe_refuses_with_advice(tmp_path, drives, capsys):
    cfg = tmp_path / "bench.toml"
    cfg.write_text(CONFIG.replace("max_v = 20.0", "max_v = 1.0"))  # SIDBE at amplitude 2 reaches ~1.5
    out = tmp_path / "o"
    rc = main(["commission", "--drive", "sim://?pace=fast", "--yes", "--config", str(cfg), "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 1
    assert "exceeds the limit 1" in err and "Lower the excitation ([sidbe] amplitude" in err
    assert drives[-1].device.state is PowerState.DISABLED and drives[-1].device.command == 0.0
    assert read_log(out / "bump.csv").complete
    partial = (out / "log-1.csv").read_text()  # kept, marked incomplete with the reason
    assert "# status = incomplete" in partial and "exceeds the limit" in partial
