"""Issue 12: diagnose says when the model does not explain the data, and names nothing false.

Plants the workflow was not tuned on, each with explicit seeds; only the log
goes to the diagnosis. The truth each case is checked against is the
generator's own: the hidden effects, and the sensor noise it added (the
noise floor must find it from the data). Each case is diagnosed once, in
the test worker, the first time a test reads it, and shared across the module.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest

from servobench.bench.cli import main
from servobench.bench.diagnose.workflow import diagnose
from servobench.bench.log.io import read_log
from servobench.bench.report.diagnose import summary_lines, to_json
from servobench.bench.testing.hidden_effects import (
    CaseResults,
    HiddenCase,
    issue_case,
    random_case,
    write_case_log,
)
from servobench.sim_backend.physics import effects as library
from servobench.sim_backend.physics.plant import PlantParams

pytestmark = pytest.mark.slow  # eight diagnoses, one after the other

WITHOUT_POSITION = tuple(n for n in library.names() if n != "position_friction")


def strong_stribeck(_rng) -> HiddenCase:
    """A Stribeck peak 2.5 times the Coulomb level on a weakly damped axis, one triangle run: the
    best linear-plus-Coulomb fit has a negative viscous coefficient."""
    p = PlantParams(M=0.1, B=0.3, coulomb_pos=0.5, coulomb_neg=0.4, noise=0.004)
    effects = {"stribeck": {"fs": 1.25, "vs": 0.8}}
    return HiddenCase("stribeck", p.with_changes(effects=effects), 1.4, effects, "triangle")


#: name -> (seed, case maker, effects the search may name (None: all)).
CASES = {
    "issue": (12, issue_case, None),
    "issue_without_position_friction": (12, issue_case, WITHOUT_POSITION),
    "strong_stribeck": (5, strong_stribeck, None),
    "square_stribeck": (1, lambda rng: random_case("stribeck", rng, inputs="square"), None),
    "sine_control": (2, lambda rng: random_case(None, rng, inputs="sine"), None),
    "sidbe_stribeck": (3, lambda rng: random_case("stribeck", rng, inputs="sidbe"), None),
    "coloured_control": (
        4,
        lambda rng: random_case(None, rng, noise_fraction=0.03, noise_colour_hz=5.0),
        None,
    ),
    "spring": (6, lambda rng: random_case(None, rng, outside={"spring": 1.0}), None),
}


#: The case diagnosed through the command line (``--json --out``) rather than the function.
THROUGH_CLI = "spring"


def run_case(name: str, folder: str) -> dict:
    seed, make, allowed = CASES[name]
    rng = np.random.default_rng(seed)
    case = make(rng)
    path = write_case_log(case, Path(folder) / f"{name}.csv", rng)
    log = read_log(path)
    v = np.concatenate([r.v for r in log.runs])
    truth = {
        "truth": case.effects,
        # The generator's sensor noise as a gap [%] (for coloured noise: its standard deviation).
        "true_noise": 100.0 * case.params.noise / float(np.std(v)),
        "top_speed": float(np.quantile(np.abs(v), 0.99)),
    }
    if name == THROUGH_CLI:
        return {**truth, **run_cli(path, Path(folder) / name)}
    stages: list[str] = []
    d = diagnose(log, effects=allowed, progress=stages.append)
    return {
        **truth,
        "named": [e.name for e in d.effects],
        "parameters": [e.parameters for e in d.effects],
        "json": to_json(d),
        "text": summary_lines(d),
        "start_note": d.start.note,
        "rejected": [(t.effects, t.reason) for rnd in d.trace.rounds for t in rnd.tried if not t.chosen],
        "stages": stages,
    }


def run_cli(path: Path, out: Path) -> dict:
    """``servobench diagnose LOG --json --out DIR``: its status, JSON, report and model.json."""
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        status = main(["diagnose", str(path), "--json", "--out", str(out)])
    j = json.loads(stdout.getvalue())
    return {
        "status": status,
        "json": j,
        "named": [e["name"] for e in j["effects"]],
        "report": (out / "report.md").read_text(),
        "model": json.loads((out / "model.json").read_text()),
        "rejected": [
            (tuple(c["effects"]), c["reason"])
            for rnd in j["tried"]
            for c in rnd["candidates"]
            if not c["chosen"]
        ],
    }


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> CaseResults:
    folder = str(tmp_path_factory.mktemp("verdict"))
    return CaseResults(lambda name: run_case(name, folder))


def test_issue_case_names_position_friction_and_reaches_the_noise_floor(results):
    r = results["issue"]
    j = r["json"]
    assert r["named"] == ["position_friction"], r["named"]
    assert j["verdict"] == "explained" and j["unexplained_signature"] == ""
    # The floor is the generator's 1 % sensor noise, found from the data.
    assert j["noise_floor_percent"] == pytest.approx(r["true_noise"], rel=0.2)
    assert j["gap_after"] <= 1.5 * j["noise_floor_percent"]
    assert j["gap_before"] >= 5 * j["noise_floor_percent"]
    assert r["text"][0].startswith("verdict: explained")
    assert not any("its 1-sigma allow for the sensor noise" in line for line in r["text"])


def test_issue_case_friction_curve_rises_along_the_travel_as_hidden(results):
    from servobench.sim_backend.physics.effects.position_friction import curve

    named = results["issue"]["parameters"][0]
    truth = results["issue"]["truth"]["position_friction"]
    full = library.validate("position_friction", named)
    x0, x1, table = curve(full)
    t0, t1, true_table = curve(truth)
    # Compare the two curves' rise over the part of the travel both span.
    grid = np.linspace(max(x0, t0), min(x1, t1), 50)
    got = np.interp(grid, np.linspace(x0, x1, table.size), table)
    want = np.interp(grid, np.linspace(t0, t1, true_table.size), true_table)
    assert got[-1] - got[0] == pytest.approx(want[-1] - want[0], rel=0.2)


def test_without_position_friction_the_verdict_is_unexplained_and_says_where(results):
    r = results["issue_without_position_friction"]
    j = r["json"]
    assert j["verdict"] == "unexplained"
    assert j["gap_after"] > 5 * j["noise_floor_percent"]
    sig = j["unexplained_signature"]
    assert "noise floor" in sig and "it lives against position" in sig, sig
    assert j["residual"]["places"][0]["place"] == "position"
    assert r["text"][0] == f"verdict: unexplained -- {sig}"
    assert math.isfinite(j["noise_floor_percent"]) and j["noise_floor_percent"] > 0
    # its 1-sigma allow for the noise alone, and the text says so
    cover = [line for line in r["text"] if "its 1-sigma allow for the sensor noise" in line]
    assert len(cover) == 1 and "not for what the model lacks" in cover[0], r["text"]
    assert f"a gap of {j['gap_after']:.3g}%" in cover[0]


def test_a_stribeck_peak_that_makes_the_base_fit_s_b_negative_is_named(results):
    r = results["strong_stribeck"]
    assert "B = -" in r["start_note"] and "Stribeck" in r["start_note"], r["start_note"]
    assert r["named"] == ["stribeck"], r["named"]
    assert r["parameters"][0]["fs"] == pytest.approx(1.25, rel=0.1)
    assert r["json"]["verdict"] == "explained"
    # One triangle run fixes the friction curve over the speeds it visits, not how its slope
    # splits between B and the Coulomb levels: compare the curves, each direction.
    b, s = r["json"]["base_after"], r["parameters"][0]
    assert b["B"] > 0
    speed = np.linspace(0.0, r["top_speed"], 50)
    for fc, true_fc in ((b["coulomb_pos"], 0.5), (b["coulomb_neg"], 0.4)):
        got = fc + b["B"] * speed + (s["fs"] - fc) * np.exp(-((speed / s["vs"]) ** 2))
        want = true_fc + 0.3 * speed + (1.25 - true_fc) * np.exp(-((speed / 0.8) ** 2))
        assert np.max(np.abs(got - want)) < 0.03 * 1.25


@pytest.mark.parametrize("case", ["square_stribeck", "sidbe_stribeck"])
def test_single_runs_and_sidbe_pairs_name_only_what_is_hidden(results, case):
    r = results[case]
    assert r["named"] == ["stribeck"], r["named"]
    assert r["json"]["verdict"] == "explained"


def test_a_sine_control_names_nothing(results):
    r = results["sine_control"]
    assert r["named"] == [] and r["json"]["verdict"] == "explained"


def test_sidbe_periods_give_the_period_to_period_scatter(results):
    j = results["sidbe_stribeck"]["json"]
    assert j["noise"]["repeat_percent"] == pytest.approx(results["sidbe_stribeck"]["true_noise"], rel=0.3)


def test_coloured_noise_raises_the_floor_instead_of_naming_effects(results):
    r = results["coloured_control"]
    j = r["json"]
    assert r["named"] == [], r["named"]
    assert j["verdict"] == "explained"
    assert j["noise"]["sensor_percent"] < 0.5 * r["true_noise"]  # low-passed: barely white
    assert j["noise_floor_percent"] == pytest.approx(r["true_noise"], rel=0.3)


def test_a_plant_outside_the_library_is_unexplained_and_the_command_still_succeeds(results):
    r = results[THROUGH_CLI]
    j = r["json"]
    assert r["status"] == 0
    assert j["verdict"] == "unexplained"
    assert "position" in j["unexplained_signature"]
    # The report leads with the verdict; model.json carries it with the floor.
    assert r["report"].splitlines()[2] == f"**verdict: unexplained -- {j['unexplained_signature']}**"
    assert r["model"]["verdict"] == "unexplained"
    assert r["model"]["noise_floor_percent"] == j["noise_floor_percent"]


def test_every_rejected_candidate_says_why(results):
    rejected = [t for name in CASES for t in results[name]["rejected"]]
    assert rejected
    assert all(reason for _, reason in rejected), [t for t in rejected if not t[1]]


def test_progress_names_each_stage_as_it_starts(results):
    stages = results["issue"]["stages"]
    assert stages[0] == "fitting the base model" and stages[-1].startswith("judging")
    assert "round 1: screening the effect library" in stages
    assert any(s.startswith("round 1: refitting position_friction") for s in stages), stages
