"""``servobench diagnose``: one JSON object, the comparison CSV, the report, typed errors."""

from __future__ import annotations

import contextlib
import csv
import io
import json
from pathlib import Path

import numpy as np
import pytest

from servobench.bench.cli import main
from servobench.bench.log.io import LogWriter
from servobench.bench.testing.hidden_effects import random_case, write_case_log


@pytest.fixture(scope="module")
def deadzone_log(tmp_path_factory):
    rng = np.random.default_rng(20)
    path = tmp_path_factory.mktemp("cli") / "deadzone.csv"
    return write_case_log(random_case("deadzone", rng), path, rng)


@pytest.fixture(scope="module")
def diagnosed(deadzone_log, tmp_path_factory):
    """``diagnose LOG --json --out DIR``: exit status, stdout, DIR."""
    out = tmp_path_factory.mktemp("cli") / "report"
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        status = main(["diagnose", str(deadzone_log), "--json", "--out", str(out)])
    return status, stdout.getvalue(), out


def test_json_is_one_object_and_out_writes_csv_and_report(diagnosed):
    status, text, out = diagnosed
    assert status == 0
    obj = json.loads(text)  # exactly one JSON document, nothing else on stdout
    assert text.strip().startswith("{") and text.strip().endswith("}")
    assert [e["name"] for e in obj["effects"]][:1] == ["deadzone"]
    first = obj["effects"][0]
    assert set(first) == {"name", "parameters", "evidence", "rivals"}
    assert isinstance(first["rivals"], list) and "deadzone" not in first["rivals"]
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
    # The report leads with the verdict, as the JSON does.
    assert list(obj)[:3] == ["verdict", "noise_floor_percent", "unexplained_signature"]
    lines = report.splitlines()
    assert lines[0] == "# servobench diagnose" and lines[2].startswith(f"**verdict: {obj['verdict']}")
    # Both base fits, labelled, with the JSON's numbers.
    head = next(line for line in lines if line.startswith("| parameter |"))
    assert "base fit, before any effect" in head and "final model, refitted with deadzone" in head
    row = next(line for line in lines if line.startswith("| M |")).split("|")
    assert float(row[2]) == pytest.approx(obj["base_before"]["M"], rel=1e-3)
    assert float(row[3]) == pytest.approx(obj["base_after"]["M"], rel=1e-3)
    assert obj["base_before"]["M"] != pytest.approx(obj["base_after"]["M"], rel=1e-3)


def test_model_json_validates_to_diagnose_s_gap_and_the_report_s_url_is_the_plant(
    diagnosed, deadzone_log, capsys
):
    from servobench.sim_backend.simurl import plant_from_url

    _, text, out = diagnosed
    obj = json.loads(text)
    model = json.loads((out / "model.json").read_text())
    assert model["effects"]["deadzone"] == obj["effects"][0]["parameters"]
    assert {k: model[k] for k in ("M", "B", "coulomb_pos", "coulomb_neg")} == {
        k: obj["base_after"][k] for k in ("M", "B", "coulomb_pos", "coulomb_neg")
    }
    assert model["units"]["deadzone.width"] == model["units"]["u"]
    assert main(["validate", str(out / "model.json"), str(deadzone_log), "--json"]) == 0
    checked = json.loads(capsys.readouterr().out)
    assert checked["effects"] == [e["name"] for e in obj["effects"]]
    assert checked["gap_percent"] == pytest.approx(obj["gap_after"], rel=1e-6)
    # The report's sim:// URL is the same plant (what serve-sim and the sim drive take).
    report = (out / "report.md").read_text()
    url = next(w.strip("`") for w in report.split() if w.startswith("`sim://"))
    assert url == model["sim_url"] == obj["sim_url"]
    plant = plant_from_url(url)
    assert float(plant.M) == pytest.approx(model["M"], rel=1e-9)
    assert plant.coulomb_neg == pytest.approx(model["coulomb_neg"], rel=1e-9)
    assert plant.effects["deadzone"]["width"] == pytest.approx(
        model["effects"]["deadzone"]["width"], rel=1e-9
    )


def test_text_output_names_the_effect(deadzone_log, tmp_path, capsys, monkeypatch):
    # The log of a run cut short (no 'status = complete' trailer), in newtons and metres.
    cut = tmp_path / "cut.csv"
    text = deadzone_log.read_text()
    units = "# unit_u = N\n# unit_v = m/s\n# unit_x = m\n"
    cut.write_text(units + text[: text.rindex("# status = complete")])
    from servobench.bench.report import diagnose_figures

    axes = {}  # what each figure's axes show, captured as the report saves them

    def keep_axes(fig, path, dpi=None):
        axes[Path(path).name] = [(a.get_xlabel(), a.get_ylabel(), a.get_xscale()) for a in fig.axes]
        return save_png(fig, path, dpi=dpi)

    save_png = diagnose_figures.save_png
    monkeypatch.setattr(diagnose_figures, "save_png", keep_axes)
    assert main(["diagnose", str(cut), "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert "1. deadzone" in out and "velocity gap" in out
    lines = out.splitlines()
    assert lines[0].startswith("verdict: explained -- ")
    # Said so, as identify does.
    assert "note: the log is incomplete (no 'status = complete' trailer)" in out
    named = next(x for x in lines if x.startswith("1. "))
    assert named.startswith("1. deadzone (width=") and named.endswith(" N)"), named
    assert any(line.startswith("diagnosed plant: sim://?M=") for line in lines)
    # Issue 13: the log's units on the axes, a logarithmic residual spectrum, captions.
    assert axes["residual_spectrum.png"] == [("frequency [Hz]", "residual PSD [(m/s)^2/Hz]", "log")]
    assert [a[0] for a in axes["residual_vs_state.png"]] == ["velocity [m/s]", "position [m]"]
    report = (tmp_path / "out" / "report.md").read_text()
    assert "*Figure 2. Power spectral density of the velocity residual" in report
    assert any(x.startswith("| M | ") and x.endswith(" | kg |") for x in report.splitlines())


def test_progress_on_a_terminal_shows_the_stage_and_the_time():
    import io

    from rich.console import Console

    from servobench.bench.commands.diagnose import stage_progress

    screen = io.StringIO()
    with stage_progress(Console(file=screen, force_terminal=True, width=100)) as say:
        say("round 1: refitting stribeck (1/3)")
    shown = screen.getvalue()
    assert "round 1: refitting stribeck (1/3)" in shown and "diagnose: done in" in shown
    quiet = io.StringIO()
    with stage_progress(Console(file=quiet, force_terminal=False)) as say:
        say("round 1")
    assert quiet.getvalue() == ""


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
