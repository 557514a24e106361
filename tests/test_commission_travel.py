"""Issue 11 in commissioning: finite travel in bench.toml, SIDBE in closed loop, the whole record."""

from __future__ import annotations

import json
import struct

import numpy as np
from test_commission_cli import CONFIG, check_record

from servobench.bench.cli import main
from servobench.bench.log.io import ExperimentLog, RunData, read_log


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
    html = (out / "report.html").read_text()  # the record says how the axis was excited
    assert "closed: host-side position loop, designed from the bump test" in html
    assert "excited in closed loop" in html and "against the held one and the travel limits" in html
    share = sidbe["hold"]["travel_share"]
    assert f"{share:.0%} of the room of" in html and 0 < share <= 0.8


def test_the_closed_loop_excitation_figure_shows_excitation_total_and_travel():
    """Three panels (the position in its window) for a closed-loop log, two in open loop:
    the embedded PNG's height tells (its IHDR field, PNG specification 11.2.2)."""
    from servobench.bench.report.commission_figures import excitation_period
    from servobench.units import SignalUnits

    t = np.arange(200) * 1e-3
    u_exc = np.where(np.sin(2 * np.pi * 7 * t) >= 0, 1.0, -1.0)
    closed = ExperimentLog((RunData(1, t, u_exc + 0.1, 0 * t, 0.01 * np.sin(t), u_exc=u_exc, x_ref=0 * t),),
                           {"samples_per_period": "100"}, 1000.0)  # fmt: skip
    units = SignalUnits("N", "m/s", "m")
    height = lambda png: struct.unpack(">I", png[20:24])[0]  # noqa: E731
    tall = height(excitation_period(closed, units, (-0.05, 0.05)))
    opened = ExperimentLog((RunData(1, t, u_exc, 0 * t, 0 * t),), {"samples_per_period": "100"}, 1000.0)
    assert tall > 1.2 * height(excitation_period(opened, units))


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
