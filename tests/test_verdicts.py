"""The verdict contract (issue 24): exit status, first line and ``--json``'s first key agree.

0 only for a pass, 3 for a command that ran to the end with a fail, 1 for an
error (an axis that never moved above the sensor noise), 130 for Ctrl-C; one
place maps a verdict to the exit status.
"""

from __future__ import annotations

import json

from servobench.bench.cli import main
from servobench.bench.report.summary import rate_text
from servobench.verdict import EXIT_FAIL, EXIT_PASS, Verdict, exit_status

#: An axis whose Stribeck breakaway (1.0) is the amplitude: it never leaves the noise.
STUCK = "sim://?noise=0.01&seed=1&stribeck_fs=1.0&stribeck_vs=0.3"
#: A plain axis with sensor noise.
PLAIN = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4&noise=0.002&seed=3"
QUICK = ["--periods", "3", "--period", "1", "--no-plots"]


def test_one_mapping_from_verdict_to_exit_status():
    assert [exit_status(v) for v in Verdict] == [EXIT_PASS, EXIT_PASS, EXIT_FAIL]
    assert exit_status(None) == 0 and exit_status(1) == 1 and exit_status(130) == 130
    assert Verdict.FAIL.line("x") == "FAIL: x" and Verdict.REMARKS.line("y") == "PASS with remarks: y"


def test_sidbe_on_an_axis_that_never_moves_is_an_error_without_a_model(tmp_path, capsys):
    out = tmp_path / "run"
    rc = main(["sidbe", "--drive", STUCK, "--max-iterations", "1", "--out", str(out), *QUICK])
    captured = capsys.readouterr()
    assert rc == 1
    err = [line for line in captured.err.splitlines() if line.startswith("servobench")]
    assert len(err) == 1 and err[0].startswith("servobench: error: ")
    assert "no motion above the sensor noise" in err[0] and "the axis never moved" in err[0]
    assert "raise the amplitude" in err[0] and "brake" in err[0]
    assert f"the logs are kept in {out}" in err[0]
    assert not (out / "model.json").exists() and (out / "log-1.csv").exists()
    assert "M =" not in captured.out


def test_sidbe_grows_the_amplitude_until_the_axis_moves(tmp_path, capsys):
    """The same axis with step 6's rounds: the larger amplitude moves it, and a model results."""
    out = tmp_path / "run"
    rc = main(["sidbe", "--drive", STUCK, "--max-iterations", "4", "--fit-threshold", "50",
               "--out", str(out), "--json", *QUICK])  # fmt: skip
    obj = json.loads(capsys.readouterr().out)
    assert rc == 0 and list(obj)[0] == "verdict" and obj["verdict"] == "pass"
    assert obj["iterations"][0]["fit_percent"] is None and "no motion above the sensor noise" in obj["iterations"][0]["error"]
    assert 0.05 < obj["M"] < 0.2


def test_sidbe_below_its_threshold_fails_with_status_3(tmp_path, capsys):
    rc = main(["sidbe", "--drive", PLAIN, "--max-iterations", "1", "--fit-threshold", "99.99",
               "--out", str(tmp_path / "run"), *QUICK])  # fmt: skip
    out = capsys.readouterr().out
    assert rc == 3
    first = out.splitlines()[0]
    assert first.startswith("FAIL: SIDBE verification fit ") and "< threshold 99.99 %" in first
    assert "servobench diagnose" in first
    saved = json.loads((tmp_path / "run" / "model.json").read_text())
    assert list(saved)[0] == "verdict" and saved["verdict"] == "fail"


def test_sidbe_that_meets_its_threshold_passes_with_status_0(tmp_path, capsys):
    rc = main(["sidbe", "--drive", PLAIN, "--max-iterations", "1", "--fit-threshold", "80",
               "--out", str(tmp_path / "run"), "--json", *QUICK])  # fmt: skip
    obj = json.loads(capsys.readouterr().out)
    assert rc == 0 and list(obj)[0] == "verdict" and obj["verdict"] == "pass"


def test_sidbe_text_keeps_the_whole_output_folder_and_says_what_a_lock_step_rate_is(tmp_path, capsys):
    deep = tmp_path / ("a-rather-long-folder-name-" * 3) / "run"
    rc = main(["sidbe", "--drive", PLAIN, "--max-iterations", "1", "--fit-threshold", "80",
               "--out", str(deep), *QUICK])  # fmt: skip
    out = capsys.readouterr().out
    assert rc == 0 and out.splitlines()[0].startswith("PASS: ")
    assert f"output: {deep}" in out.splitlines()
    text = " ".join(out.split())
    assert "Hz achieved" not in text and "lock-step" in text
    rate = rate_text(1000.0, 2.0e5, pace="fast")
    assert rate == "1000 Hz on the drive's clock (lock-step, pace=fast: streamed 200x faster than real time)"
    assert rate_text(1000.0, 998.7) == "1000 Hz set, 998.7 Hz achieved"


def test_validate_leads_with_its_verdict_and_exits_by_it(tmp_path, capsys):
    log = tmp_path / "log.csv"
    assert main(["run", "--drive", PLAIN, "--out", str(log), "--periods", "3", "--period", "1"]) == 0
    capsys.readouterr()
    assert main(["identify", str(log), "--json"]) == 0
    model = tmp_path / "model.json"
    model.write_text(capsys.readouterr().out)
    assert main(["validate", str(model), str(log)]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith("PASS: ") and ">= 90 %" in first and "<= 10 %" in first
    assert main(["validate", str(model), str(log), "--min-fit", "99.99", "--json"]) == 3
    obj = json.loads(capsys.readouterr().out)
    assert list(obj)[0] == "verdict" and obj["verdict"] == "fail"
    assert obj["thresholds"] == {"min_fit_percent": 99.99, "max_gap_percent": 10.0}
    # a wrong model: four times the inertia and a fifth of the friction fails the default thresholds
    wrong = json.loads(model.read_text())
    wrong.update(M=4 * wrong["M"], coulomb_pos=0.1, coulomb_neg=0.1)
    model.write_text(json.dumps(wrong))
    assert main(["validate", str(model), str(log)]) == 3
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith("FAIL: ") and "below 90 %" in first
