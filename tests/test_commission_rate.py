"""``commission`` streams at the rate the drive's link carries (issue 10 §4), as ``sidbe`` does.

A ``sim://`` drive that declares the limit of a Modbus RTU link at 115200 baud
(137 cycles/s, :meth:`Drive.max_rate_hz`): without ``[bump] fs_hz`` and
``[sidbe] fs_hz`` both the bump test and SIDBE run at 100 Hz; a rate beyond the
link in the config is refused before anything is enabled, in one line naming
the rate the link carries.
"""

from __future__ import annotations

import json

import pytest
from test_commission_cli import CONFIG, PLANT

import servobench.drivers.registry
from servobench.bench.cli import main
from servobench.bench.log.io import read_log
from servobench.drivers.sim import SimDrive

#: What one FC23 cycle of servobench-sim.toml takes over RTU at 115200 baud (test_link_rate.py).
RTU_LIMIT_HZ = 137.0


class OverRtu(SimDrive):
    """The simulated drive behind a link that carries RTU_LIMIT_HZ cycles a second."""

    enables = 0

    def max_rate_hz(self) -> float:
        return RTU_LIMIT_HZ

    def _enable(self):
        type(self).enables += 1
        super()._enable()


@pytest.fixture
def over_rtu(monkeypatch) -> type[OverRtu]:
    """Every drive commission opens is an :class:`OverRtu`."""
    OverRtu.enables = 0
    monkeypatch.setattr(servobench.drivers.registry, "open_drive", OverRtu)
    return OverRtu


def commission(tmp_path, extra: str = "") -> int:
    config = tmp_path / "bench.toml"
    config.write_text(CONFIG + extra)
    rc = main(["commission", "--drive", "sim://?pace=fast", "--yes", "--config", str(config),
               "--out", str(tmp_path / "rec")])  # fmt: skip
    return rc


def test_bump_and_sidbe_follow_the_link_rate(tmp_path, over_rtu, capsys):
    assert commission(tmp_path) == 0, capsys.readouterr().err
    rec = tmp_path / "rec"
    assert float(read_log(rec / "bump.csv").metadata["fs"]) == 100.0
    log = read_log(rec / "log.csv")
    assert float(log.metadata["fs"]) == 100.0
    assert all(len(run) == 300 for run in log.runs)  # 3 periods of 1 s at 100 Hz
    model = json.loads((rec / "model.json").read_text())
    for key, true in PLANT.items():
        assert model[key] == pytest.approx(true, rel=0.01), key


@pytest.mark.parametrize(
    ("extra", "option"),
    [("\n[bump]\nfs_hz = 1000.0\n", "[bump] fs_hz"), ("fs_hz = 500.0\n", "[sidbe] fs_hz")],
)
def test_a_configured_rate_beyond_the_link_is_refused_before_anything_moves(
    tmp_path, over_rtu, capsys, extra, option
):
    assert commission(tmp_path, extra) == 1
    err = capsys.readouterr().err.strip()
    asked = extra.split("=")[1].strip().rstrip("0").rstrip(".")
    assert len(err.splitlines()) == 1
    assert err.startswith(
        f"servobench: error: {option} {asked} Hz is beyond the sim:// link: it carries at most 137 "
        f"cycles/s; use {option} 100 (the default there) or less"
    )
    assert over_rtu.enables == 0 and not (tmp_path / "rec" / "bump.csv").exists()
    status = json.loads((tmp_path / "rec" / "commission.json").read_text())
    assert status["steps_done"] == []
