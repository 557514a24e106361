"""``identify --out`` and ``servobench program`` (issue 24, defect 9).

The values ``program`` prints are checked against the commissioning design
functions called directly, and the drive's own units against the scale
factors written into the log header by hand.
"""

from __future__ import annotations

import csv
import io
import json

import pytest
import tomllib

from servobench.bench.cli import main
from servobench.bench.commission.design import design_pi, friction_feed_forward

PLAIN = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4&noise=0.002&seed=3"
FF_POS = "friction feed-forward, positive motion (Coulomb +)"
FF_NEG = "friction feed-forward, negative motion (Coulomb -)"
VISCOUS = "viscous feed-forward (B)"
KP, KI = "velocity PI: proportional gain Kp", "velocity PI: integral gain Ki = Kp/Ti"
#: A drive whose command is per mille of a rated torque of 0.64 N m, velocity in rpm.
SCALE = {"scale_u": 0.00064, "scale_u_source": "0x6076 rated torque 640 mN m, per mille",
         "scale_v": 0.10471975511965977, "scale_v_source": "0x60A9 rpm"}  # fmt: skip


@pytest.fixture(scope="module")
def logged(tmp_path_factory):
    """A log of the plain axis, whose header states the drive's scale factors."""
    tmp = tmp_path_factory.mktemp("program")
    log = tmp / "log.csv"
    assert main(["run", "--drive", PLAIN, "--out", str(log), "--periods", "3", "--period", "1"]) == 0
    text = log.read_text()
    log.write_text("".join(f"# {k} = {v}\n" for k, v in SCALE.items()) + text)
    return log


def _program(capsys, *args: str) -> str:
    capsys.readouterr()
    assert main(["program", *args]) == 0
    return capsys.readouterr().out


def test_identify_out_writes_model_json_and_plots_and_refuses_to_overwrite(logged, tmp_path, capsys):
    out = tmp_path / "ident"
    assert main(["identify", str(logged), "--out", str(out)]) == 0
    model = json.loads((out / "model.json").read_text())
    assert {"M", "B", "coulomb_pos", "coulomb_neg", "fit_percent", "units"} <= set(model)
    assert model["fs"] == 1000 and model["drive_scale"]["u"] == pytest.approx(0.00064)
    assert model["M"] == pytest.approx(0.1, rel=0.03)
    assert sorted(p.name for p in out.glob("*.png")) == ["frf.png", "friction.png", "time.png"]
    assert f"output: {out}" in capsys.readouterr().out
    assert main(["identify", str(logged), "--out", str(out)]) == 1
    assert "already holds a model.json" in capsys.readouterr().err


def test_program_gives_the_commissioning_design_in_si_and_drive_units(logged, tmp_path, capsys):
    out = tmp_path / "ident"
    assert main(["identify", str(logged), "--out", str(out)]) == 0
    model = json.loads((out / "model.json").read_text())
    doc = json.loads(_program(capsys, str(out / "model.json"), "--format", "json"))
    assert doc["fs"] == 1000 and "identified base model" in doc["source"]
    rows = {r["name"]: r for r in doc["values"]}
    # the loop's delay: one cycle plus the drive's identified action delay
    pi = design_pi(model["M"], model["B"], 1000.0, delay_cycles=1.0 + model["delay_s"] * 1000.0)
    ff = friction_feed_forward(model["B"], model["coulomb_pos"], model["coulomb_neg"])
    assert rows[FF_POS]["value"] == pytest.approx(ff.coulomb_pos) and rows[FF_POS]["unit"] == "N m"
    assert rows[FF_POS]["drive_value"] == pytest.approx(ff.coulomb_pos / 0.00064)  # per mille
    assert rows[FF_NEG]["value"] == pytest.approx(ff.coulomb_neg)
    assert rows[VISCOUS]["value"] == pytest.approx(model["B"]) and rows[VISCOUS]["unit"] == "N m s/rad"
    assert rows[KP]["value"] == pytest.approx(pi.kp) and rows[KI]["value"] == pytest.approx(pi.ki)
    assert rows[KP]["drive_value"] == pytest.approx(pi.kp * SCALE["scale_v"] / 0.00064)
    assert "1 drive u unit = 0.00064 N m (0x6076 rated torque 640 mN m, per mille)" in doc["drive_units"]

    table = list(csv.DictReader(io.StringIO(_program(capsys, str(out / "model.json"), "--format", "csv"))))
    assert float(next(r for r in table if r["name"] == FF_POS)["value"]) == pytest.approx(ff.coulomb_pos, rel=1e-5)
    toml = tomllib.loads(_program(capsys, str(out / "model.json"), "--format", "toml"))
    assert toml["fs"] == 1000 and len(toml["value"]) == len(doc["values"])
    assert next(v for v in toml["value"] if v["name"] == KI)["value"] == pytest.approx(pi.ki)
    text = _program(capsys, str(out / "model.json"), "--fs", "4000")
    assert text.splitlines()[1].startswith("velocity loop at 4000 Hz")
    assert f"{FF_POS}: {ff.coulomb_pos:.6g} N m  = {ff.coulomb_pos / 0.00064:.6g} drive u unit" in text


def test_program_from_identify_json_needs_a_rate_or_says_so(logged, tmp_path, capsys):
    bare = tmp_path / "bare.json"
    assert main(["identify", str(logged), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    bare.write_text(json.dumps({k: doc[k] for k in ("M", "B", "coulomb_pos", "coulomb_neg", "units")}))
    assert main(["program", str(bare)]) == 1
    assert "states no loop rate (fs): give --fs HZ" in capsys.readouterr().err
    text = _program(capsys, str(bare), "--fs", "1000", "--log", str(logged))
    assert "drive u unit" in text  # the scale factors from the log named


def test_program_takes_a_records_program_source_and_a_diagnosed_models_base(tmp_path, capsys):
    base = {"M": 0.1, "B": 1.08, "coulomb_pos": 0.388, "coulomb_neg": 0.302, "fs": 1000.0,
            "units": {"u": "N m", "v": "rad/s", "x": "rad"}}  # fmt: skip
    record = tmp_path / "record.json"
    record.write_text(json.dumps({**base, "program_source": {
        "model": "diagnose", "description": "the diagnosed model: the base refitted together with backlash",
        "M": 0.0998, "B": 0.999, "coulomb_pos": 0.504, "coulomb_neg": 0.4005}}))  # fmt: skip
    rows = {r["name"]: r for r in json.loads(_program(capsys, str(record), "--format", "json"))["values"]}
    assert rows[FF_POS]["value"] == pytest.approx(0.504) and rows[VISCOUS]["value"] == pytest.approx(0.999)
    diagnosed = tmp_path / "diagnosed.json"
    diagnosed.write_text(json.dumps({"base_after": {**base, "coulomb_pos": 0.5}, "base_before": base,
                                     "effects": [{"name": "backlash", "parameters": {"gap": 0.05, "ratio": 0.5}}],
                                     "units": base["units"]}))  # fmt: skip
    doc = json.loads(_program(capsys, str(diagnosed), "--format", "json", "--fs", "500"))
    assert "refitted together with backlash" in doc["source"]
    assert {r["name"]: r for r in doc["values"]}[FF_POS]["value"] == pytest.approx(0.5)
