"""auto: compares SIDBE and joint on held-out data and says why; result object contract."""

import json
import math

import numpy as np
import pytest

from servobench.bench.identify.auto import identify
from servobench.bench.log.io import ExperimentLog
from servobench.bench.model.servo import IdentificationResult, ServoModel, fit_percent
from servobench.bench.procedure.excitation import make_design
from servobench.bench.testing.synthetic import simulate_experiment
from servobench.errors import IdentificationError, UsageError
from servobench.sim_backend.physics.plant import PlantParams

TRUE = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)
CONTRACT = {
    "M",
    "B",
    "pole",
    "dc_gain",
    "coulomb_pos",
    "coulomb_neg",
    "fit_percent",
    "method",
    "std",
    "selection",
}


def test_auto_picks_joint_at_low_amplitude_and_explains():
    r = identify(simulate_experiment(TRUE, make_design(1.0)), "auto")
    assert r.method == "joint"
    assert set(r.validation) == {"sidbe", "joint"}
    assert r.validation["joint"] > r.validation["sidbe"]
    assert "held-out last period" in r.selection and "joint" in r.selection
    assert r.frf is not None  # the measured FRF is kept for the plot


def test_auto_with_two_periods_scores_in_sample():
    r = identify(simulate_experiment(TRUE, make_design(5.0, periods=2)), "auto")
    assert "in-sample" in r.selection


def test_auto_on_a_single_run_falls_back_to_joint():
    log = simulate_experiment(TRUE, make_design(2.0))
    single = ExperimentLog(log.runs[:1], log.metadata, log.fs_hz)
    r = identify(single, "auto")
    assert r.method == "joint" and "sidbe cannot run" in r.selection


def test_result_json_contract():
    r = identify(simulate_experiment(TRUE, make_design(2.0)), "auto")
    assert isinstance(r, IdentificationResult)
    out = json.loads(json.dumps(r.to_json()))
    assert set(out) >= CONTRACT
    assert out["pole"] == pytest.approx(-out["B"] / out["M"])
    assert out["dc_gain"] == pytest.approx(1 / out["B"])
    assert set(out["std"]) == {"M", "B", "coulomb_pos", "coulomb_neg", "delay_s"}
    assert out["delay_s"] == pytest.approx(0.0, abs=1e-9)  # a lock-step log: no action delay
    assert out["coulomb_pos"] >= 0 and out["coulomb_neg"] >= 0


def test_unknown_method_is_a_usage_error():
    with pytest.raises(UsageError):
        identify(simulate_experiment(TRUE, make_design(2.0)), "magic")


def test_servo_model_api():
    m = ServoModel(0.1, 1.0, 0.5, 0.4)
    assert m.pole == -10.0 and m.dc_gain == 1.0
    p = m.to_plant_params()
    assert (p.M, p.B, p.coulomb_pos, p.coulomb_neg) == (0.1, 1.0, 0.5, 0.4)
    resp = m.simulate(np.full(3000, 2.0), 1000.0)
    # steady state (u - coulomb_pos)/B
    assert resp.v[-1] == pytest.approx(1.5, rel=1e-6)
    assert resp.x.shape == (3000,)
    with pytest.raises(IdentificationError):
        ServoModel(-0.1, 1.0, 0.0, 0.0)
    with pytest.raises(IdentificationError):
        ServoModel(0.1, 1.0, -0.1, 0.0)


def test_fit_percent_definition():
    v = np.array([0.0, 1.0, 2.0, 3.0])
    assert fit_percent(v, v) == 100.0
    assert fit_percent(v, np.full(4, v.mean())) == pytest.approx(0.0)
    assert fit_percent(np.ones(3), np.zeros(3)) == -math.inf


def test_incomplete_log_is_identified_with_a_note(tmp_path):
    from servobench.bench.log.io import read_log

    log = simulate_experiment(TRUE, make_design(2.0, periods=2, period_s=1.0))
    path = tmp_path / "cut.csv"
    rows = [
        f"1,{t:.6f},{u:.10g},{v:.10g}"
        for t, u, v in zip(log.runs[0].t, log.runs[0].u, log.runs[0].v, strict=True)
    ]
    path.write_text(
        "# fs = 1000\n# status = incomplete\nrun,t,u,v\n" + "\n".join(rows[:1500]) + "\n"
    )
    r = identify(read_log(path), "auto")
    assert any("incomplete" in n for n in r.notes)
    assert r.model.pole == pytest.approx(-10.0, rel=1e-3)
