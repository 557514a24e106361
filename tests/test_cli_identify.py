"""CLI contract: ``servobench run`` / ``identify`` / ``sidbe`` with --json print exactly one JSON object."""

import json
import os
import subprocess
import sys

import pytest

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


def servobench(*args, cwd=None, env=None):
    return subprocess.run(
        [sys.executable, "-m", "servobench", *args],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=cwd,
        env=env,
    )


def one_json(stdout: str) -> dict:
    text = stdout.strip()
    obj, end = json.JSONDecoder().raw_decode(text)
    assert text[end:].strip() == "", "more than one JSON object on stdout"
    assert isinstance(obj, dict)
    return obj


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli") / "log.csv"
    p = servobench(
        "run", "--drive", "sim://", "--out", str(path), "--amplitude", "2", "--periods", "3"
    )
    assert p.returncode == 0, p.stderr
    assert "wrote" in p.stdout
    return path


def test_identify_json_contract(sim_log):
    p = servobench("identify", str(sim_log), "--json")
    assert p.returncode == 0, p.stderr
    out = one_json(p.stdout)
    assert set(out) >= CONTRACT
    assert out["M"] == pytest.approx(0.1, rel=1e-3) and out["B"] == pytest.approx(1.0, rel=1e-3)
    assert out["coulomb_pos"] == pytest.approx(0.5, rel=1e-3)
    assert out["coulomb_neg"] == pytest.approx(0.4, rel=1e-3)
    assert out["pole"] == pytest.approx(-10.0, rel=1e-3) and out["dc_gain"] == pytest.approx(
        1.0, rel=1e-3
    )
    assert out["method"] in ("joint", "sidbe") and out["selection"].startswith("auto")
    assert set(out["std"]) == {"M", "B", "coulomb_pos", "coulomb_neg", "delay_s"}


@pytest.mark.parametrize("method", ["sidbe", "joint"])
def test_identify_methods_and_human_summary(sim_log, method, tmp_path):
    p = servobench("identify", str(sim_log), "--method", method, "--json")
    assert p.returncode == 0, p.stderr
    assert one_json(p.stdout)["method"] == method
    p = servobench("identify", str(sim_log), "--method", method, "--plots", str(tmp_path))
    assert p.returncode == 0, p.stderr
    assert "Coulomb" in p.stdout and "fit" in p.stdout
    assert (tmp_path / "time.png").exists()


def test_sidbe_json_contract(tmp_path):
    p = servobench("sidbe", "--drive", "sim://", "--json", "--out", str(tmp_path / "out"))
    assert p.returncode == 0, p.stderr
    out = one_json(p.stdout)
    assert set(out) >= CONTRACT
    for key in ("iterations", "amplitude", "verification", "freqs", "periods"):
        assert key in out
    assert out["pole"] == pytest.approx(-10.0, rel=1e-3)
    assert out["verification"]["passed"] is True
    for name in ("log.csv", "model.json", "frf.png", "time.png", "friction.png"):
        assert (tmp_path / "out" / name).exists(), name


def test_sidbe_default_out_dir_is_timestamped(tmp_path):
    p = servobench(
        "sidbe", "--drive", "sim://", "--periods", "2", "--period", "1", "--no-plots", cwd=tmp_path
    )
    assert p.returncode == 0, p.stderr
    runs = list((tmp_path / "servobench-runs").iterdir())
    assert len(runs) == 1 and (runs[0] / "model.json").exists()
    assert "SIDBE" in p.stdout


def test_help_mentions_default_out():
    p = servobench("sidbe", "--help", env={**os.environ, "COLUMNS": "250"})
    assert "servobench-runs/<timestamp>" in p.stdout
