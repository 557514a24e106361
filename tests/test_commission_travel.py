"""Issue 11 in commissioning: finite travel in bench.toml, SIDBE in closed loop, the whole record."""

from __future__ import annotations

import json

import numpy as np
from test_commission_cli import CONFIG, check_record

from servobench.bench.cli import main
from servobench.bench.logio import read_log


def test_commission_with_finite_travel_completes_with_the_whole_record(tmp_path, capsys):
    cfg = tmp_path / "bench.toml"
    cfg.write_text(CONFIG.replace("xmin = -inf", "xmin = -0.05").replace("xmax = inf", "xmax = 0.05")
                   .replace("period_s = 1.0", "period_s = 2.0"))  # fmt: skip
    out = tmp_path / "rec"
    rc = main(["commission", "--drive", "sim://?pace=fast&noise=0.01&seed=4", "--yes", "--config", str(cfg),
               "--out", str(out)])  # fmt: skip
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert "closed loop: a hold loop keeps the axis in [-0.05, 0.05]" in captured.out
    model = check_record(out)
    assert model["coulomb_pos"] > 0 and model["coulomb_neg"] > 0
    status = json.loads((out / "commission.json").read_text())
    sidbe = status["sidbe"]
    assert sidbe["loop"] == "closed" and sidbe["hold"]["where"] == "host"
    assert "known" in sidbe["hold"]  # designed from the bump test, no relay probe
    assert not (out / "probe.csv").exists()
    for name in ("bump.csv", "log.csv"):
        for r in read_log(out / name).runs:
            assert np.all(np.abs(r.x) < 0.05)
    assert read_log(out / "log.csv").metadata["loop"] == "closed"


def test_the_loop_key_is_read_and_checked(tmp_path, capsys):
    cfg = tmp_path / "bench.toml"
    cfg.write_text(CONFIG + 'loop = "sideways"\n')
    rc = main(["commission", "--drive", "sim://?pace=fast", "--yes", "--config", str(cfg), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 1 and "unknown loop 'sideways'; choose from auto, open, closed" in err
    cfg.write_text(CONFIG + "loop = 1\n")
    rc = main(["commission", "--drive", "sim://?pace=fast", "--yes", "--config", str(cfg), "--out", str(tmp_path / "p")])
    err = capsys.readouterr().err
    assert rc == 1 and "bench.toml [sidbe]: loop must be a string, got 1" in err
