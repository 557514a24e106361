"""``servobench diagnose``: one JSON object, the comparison CSV, the report, typed errors."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from servobench.bench.cli import main
from servobench.bench.logio import LogWriter
from servobench.bench.testing.hidden_effects import random_case, write_case_log


@pytest.fixture(scope="module")
def deadzone_log(tmp_path_factory):
    rng = np.random.default_rng(20)
    path = tmp_path_factory.mktemp("cli") / "deadzone.csv"
    return write_case_log(random_case("deadzone", rng), path, rng)


def test_json_is_one_object_and_out_writes_csv_and_report(deadzone_log, tmp_path, capsys):
    out = tmp_path / "report"
    assert main(["diagnose", str(deadzone_log), "--json", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    obj = json.loads(text)  # exactly one JSON document, nothing else on stdout
    assert text.strip().startswith("{") and text.strip().endswith("}")
    assert [e["name"] for e in obj["effects"]][:1] == ["deadzone"]
    first = obj["effects"][0]
    assert set(first) == {"name", "parameters", "evidence"}
    assert first["parameters"]["width"] > 0 and "dead band" in first["evidence"]
    assert obj["gap_after"] < obj["gap_before"]
    with open(out / "comparison.csv", newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["run", "t", "v_measured", "v_before", "v_after"]
    assert {r[0] for r in rows[1:]} == {"1", "2"} and len(rows) == 2001
    v_meas = np.array([float(r[2]) for r in rows[1:]])
    v_after = np.array([float(r[4]) for r in rows[1:]])
    gap = 100 * np.sqrt(np.mean((v_after - v_meas) ** 2)) / np.std(v_meas)
    assert gap == pytest.approx(obj["gap_after"], rel=1e-6)
    report = (out / "report.md").read_text()
    assert "deadzone" in report
    for png in ("residual_vs_state.png", "residual_spectrum.png", "overlay.png", "gap_steps.png"):
        assert (out / png).stat().st_size > 1000 and png in report


def test_text_output_names_the_effect(deadzone_log, capsys):
    assert main(["diagnose", str(deadzone_log)]) == 0
    out = capsys.readouterr().out
    assert "1. deadzone" in out and "velocity gap" in out


def test_missing_log_is_one_line_error(tmp_path, capsys):
    assert main(["diagnose", str(tmp_path / "nope.csv")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("servobench: error: no such log file")


def test_log_without_motion_is_an_identification_error(tmp_path, capsys):
    path = tmp_path / "still.csv"
    with LogWriter(path, {"fs": 500}) as w:
        n = 200
        w.append_block(np.ones(n), np.arange(n) / 500, np.zeros(n), np.zeros(n), np.zeros(n))
    assert main(["diagnose", str(path), "--json"]) == 1
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and "does not move" in err[0]
    # under --json stdout holds exactly one object: the error, as stderr words it (issue 13)
    assert json.loads(captured.out) == {"error": err[0].removeprefix("servobench: error: ")}


def test_bad_horizon_is_a_usage_error(deadzone_log, capsys):
    assert main(["diagnose", str(deadzone_log), "--horizon", "-1"]) == 1
    assert "horizon must be > 0" in capsys.readouterr().err
