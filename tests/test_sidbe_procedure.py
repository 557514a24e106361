"""The SIDBE procedure on the simulated drive, including step 6."""

import json

import pytest
from numpy.testing import assert_allclose

from servobench.bench.log.io import read_log
from servobench.bench.procedure.sidbe import SidbeOptions, run_sidbe
from servobench.drivers.registry import open_drive
from servobench.errors import UsageError

FAST = {"period_s": 2.0, "periods": 3}


def test_default_sim_drive_is_identified_and_files_written(tmp_path):
    calls = []
    r = run_sidbe(
        open_drive("sim://"),
        SidbeOptions(),
        tmp_path,
        progress=lambda i, d, t: calls.append((i, d, t)),
    )
    m = r.result.model
    assert_allclose([m.M, m.B, m.coulomb_pos, m.coulomb_neg], [0.1, 1.0, 0.5, 0.4], rtol=1e-3)
    assert r.passed and len(r.iterations) == 1 and r.iterations[0].action == "accepted"
    assert {p.name for p in r.plots} == {"frf.png", "time.png", "friction.png"}
    for p in r.plots:
        assert p.stat().st_size > 10_000
    log = read_log(tmp_path / "log.csv")
    assert log.complete and [x.run for x in log.runs] == [1, 2]
    for key in ("fs", "amplitude", "ratio", "freqs", "periods", "samples_per_period"):
        assert key in log.metadata
    saved = json.loads((tmp_path / "model.json").read_text())
    assert saved["M"] == pytest.approx(m.M) and saved["verification"]["passed"] is True
    assert calls and calls[-1][1] == calls[-1][2]
    # sim:// is a rotary axis in SI unless told otherwise: the log and the model say so
    assert (log.metadata["unit_u"], log.metadata["unit_v"], log.metadata["unit_x"]) == (
        "N m", "rad/s", "rad",
    )  # fmt: skip
    assert saved["units"]["M"] == "kg m^2" and saved["units"]["B"] == "N m s/rad"
    assert saved["units"]["coulomb_pos"] == saved["units"]["coulomb_neg"] == "N m"


def test_a_linear_sim_axis_gives_a_model_in_kg_and_n(tmp_path):
    r = run_sidbe(open_drive("sim://?units=linear"), SidbeOptions(plots=False, **FAST), tmp_path)
    units = json.loads((tmp_path / "model.json").read_text())["units"]
    assert (units["M"], units["B"], units["coulomb_pos"], units["pole"]) == ("kg", "N s/m", "N", "1/s")
    assert r.result.units.x == "m"


def test_step6_raises_the_amplitude_when_the_first_try_fails(tmp_path):
    opts = SidbeOptions(amplitude=0.6, max_iterations=3, plots=False, **FAST)
    r = run_sidbe(open_drive("sim://?noise=0.05&seed=1"), opts, tmp_path)
    amps = [it.amplitude for it in r.iterations]
    assert len(amps) >= 2 and amps == sorted(amps) and amps[1] == pytest.approx(1.2)
    assert r.iterations[0].fit_percent < opts.fit_threshold
    assert "amplitude raised" in r.iterations[0].action
    assert r.passed and r.iterations[-1].action == "accepted"
    assert r.design.amplitude == amps[-1]
    assert (tmp_path / "log-1.csv").exists() and (tmp_path / "log.csv").exists()


def test_step6_redesigns_the_spectrum_at_the_amplitude_limit(tmp_path):
    opts = SidbeOptions(amplitude=0.6, max_iterations=3, plots=False, **FAST)
    r = run_sidbe(open_drive("sim://?noise=0.05&seed=1&max_u=0.6"), opts, tmp_path)
    assert not r.passed
    assert "spectrum redesigned" in r.iterations[0].action
    assert r.iterations[1].freqs_hz != r.iterations[0].freqs_hz
    assert r.iterations[-1].action.startswith("stopped")


def test_amplitude_beyond_max_u_is_refused_before_moving(tmp_path):
    with pytest.raises(UsageError, match="max_u"):
        run_sidbe(open_drive("sim://?max_u=2"), SidbeOptions(amplitude=3.0), tmp_path)
    assert not (tmp_path / "log-1.csv").exists()
