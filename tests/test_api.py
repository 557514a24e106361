"""The public Python API (issue 31): the snippet runs as written, each result's ``to_dict()`` is
what the CLI prints with ``--json`` for the same input, models round-trip through their files,
and errors are servobench exceptions with the CLI's one-line messages."""

from __future__ import annotations

import dataclasses
import importlib.util
import inspect
import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import servobench as sb
from servobench.bench.cli import main

#: A short excitation (2 periods of 2 s per run): noise-free sim:// is exact with it.
SHORT = {"periods": 2, "period_s": 2.0}
SHORT_CLI = ["--periods", "2", "--period", "2"]


@pytest.fixture(scope="module")
def snippet(tmp_path_factory):
    """The issue's snippet, as written, in a fresh folder (a short excitation); its variables."""
    folder = tmp_path_factory.mktemp("snippet")
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(folder)
        with sb.open_drive("sim://") as drive:
            result = sb.sidbe(drive, out="run", **SHORT)
        log = sb.read_log("run/log.csv")
        model = sb.identify(log)
        report = sb.diagnose(log)
        check = sb.validate(model, log)
        values = sb.program(model)
        u = log.runs[0].u
        v = model.simulate(u, fs=1000.0)
        model.save("model.json")
        same = sb.load_model("model.json")
    return SimpleNamespace(folder=folder, drive=drive, result=result, log=log, model=model, report=report,
                           check=check, values=values, u=u, v=v, same=same)  # fmt: skip


def cli_json(capsys, *argv: str, status: int | tuple[int, ...] = 0) -> dict:
    """The one JSON object ``servobench ARGV`` prints, and its exit status checked."""
    capsys.readouterr()
    rc = main(list(argv))
    out, err = capsys.readouterr()
    assert rc in (status if isinstance(status, tuple) else (status,)), err
    return json.loads(out)


def cli_error(capsys, *argv: str) -> str:
    """The one error line ``servobench ARGV`` prints on stderr (exit status 1)."""
    capsys.readouterr()
    assert main(list(argv)) == 1
    err = capsys.readouterr().err.splitlines()
    lines = [line for line in err if line.startswith("servobench: error: ")]  # beside progress bars
    assert len(lines) == 1, err
    return lines[0].removeprefix("servobench: error: ")


def message(err: BaseException) -> str:
    """The line the CLI prints for ``err`` (its message and notes)."""
    from servobench.errors import notes_of

    return "; ".join([str(err), *notes_of(err)])


# ------------------------------------------------------------------ the snippet
def test_snippet_runs_as_written(snippet):
    s = snippet
    assert not s.drive.is_open and not s.drive.enabled
    assert s.result.verdict is sb.Verdict.PASS and s.result.passed
    assert s.result.headline.startswith("PASS: SIDBE verification fit")
    assert s.result.log == Path("run/log.csv") and (s.folder / s.result.log).is_file()
    assert isinstance(s.result.model, sb.Model) and isinstance(s.log, sb.Log) and isinstance(s.model, sb.Model)
    for got in (s.result.model, s.model, s.report.model):
        assert pytest.approx(0.1, rel=1e-6) == got.M and pytest.approx(1.0, rel=1e-6) == got.B
        assert got.coulomb_pos == pytest.approx(0.5, rel=1e-6) and got.coulomb_neg == pytest.approx(0.4, rel=1e-6)
        assert got.pole == pytest.approx(-got.B / got.M) and got.dc_gain == pytest.approx(1 / got.B)
    assert s.model.delay == 0.0 and s.model.effects == {} and s.model.fs_hz == 1000.0
    assert set(s.model.std) >= {"M", "B", "coulomb_pos", "coulomb_neg", "delay_s"}
    assert s.model.units["B"] == "N m s/rad" and s.model.units["u"] == "N m"
    assert s.report.verdict == "explained" and s.report.explained and s.report.effects == {}
    assert s.report.model.delay is None  # a diagnosis states no action delay
    assert 0 <= s.report.gap_percent < 0.01 and s.report.noise_floor_percent >= 0  # noise-free: exact
    assert s.check.verdict is sb.Verdict.PASS and s.check.fit_percent > 99.9 and s.check.gap_percent < 0.01
    names = [v.name for v in s.values]
    assert len(s.values) == len(names) and any("Coulomb +" in n for n in names)
    assert s.values.fs_hz == 1000.0 and s.values.velocity_pi.kp > 0
    assert isinstance(s.v, np.ndarray) and s.v.shape == s.u.shape
    np.testing.assert_allclose(s.v, s.log.runs[0].v, atol=1e-6)
    assert s.same == s.model and s.same.to_dict() == s.model.to_dict()


def test_results_are_frozen_and_documented(snippet):
    for result in (snippet.result, snippet.model, snippet.report, snippet.check, snippet.values):
        assert dataclasses.is_dataclass(result) and type(result).__doc__
        with pytest.raises(dataclasses.FrozenInstanceError):
            result.verdict = None  # type: ignore[misc]
        assert json.loads(json.dumps(result.to_dict(), allow_nan=False)) == result.to_dict()


def test_import_is_light_and_names_are_public():
    code = "import servobench, sys; print(sorted(m for m in sys.modules if m.startswith('servobench')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert eval(out) == ["servobench", "servobench.errors", "servobench.verdict"]
    for name in sb.__all__:
        assert getattr(sb, name) is not None, name
    assert set(sb.__all__) <= set(dir(sb))
    assert issubclass(sb.IdentificationError, sb.ServobenchError) and isinstance(sb.__version__, str)
    with pytest.raises(AttributeError):
        sb.no_such_name  # noqa: B018


@pytest.mark.parametrize("name", ["sidbe", "identify", "diagnose", "validate", "program", "commission",
                                  "fleet", "read_log", "load_model", "open_drive"])  # fmt: skip
def test_every_parameter_is_documented_and_no_keyword_is_swallowed(name):
    function = getattr(sb, name)
    doc = inspect.getdoc(function)
    for parameter in inspect.signature(function).parameters:
        assert parameter in doc, f"{name}: {parameter} is not documented"
    assert not any(p.kind is p.VAR_KEYWORD for p in inspect.signature(function).parameters.values())


# ------------------------------------------------------------------ to_dict() == the CLI's --json
def _close(a, b, rel: float = 1e-9) -> bool:
    """``a`` and ``b`` equal, numbers within ``rel`` (through dicts and lists): pytest's approx
    takes numbers only (pytest 9.2 refuses a string even where the two are equal)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_close(a[k], b[k], rel) for k in a)
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(_close(x, y, rel) for x, y in zip(a, b, strict=True))
    if isinstance(a, int | float) and isinstance(b, int | float) and not isinstance(a, bool):
        return a == pytest.approx(b, rel=rel)
    return a == b


def test_sidbe_matches_the_cli(snippet, tmp_path, capsys):
    api = snippet.result.to_dict()
    assert api == json.loads((snippet.folder / "run" / "model.json").read_text())
    cli = cli_json(capsys, "sidbe", "--drive", "sim://", *SHORT_CLI, "--json", "--out", str(tmp_path / "cli"))
    assert list(api) == list(cli)
    for key in ("verdict", "M", "B", "coulomb_pos", "coulomb_neg", "delay_s", "fit_percent", "method", "units",
                "amplitude", "ratio", "fs", "periods", "freqs", "loop"):  # fmt: skip
        assert _close(api[key], cli[key]), (key, api[key], cli[key])
    assert snippet.result.model == sb.load_model(snippet.folder / snippet.result.model_file)


def test_sidbe_takes_every_option_of_the_procedure():
    from servobench.bench.procedure.sidbe import SidbeOptions

    keywords = inspect.signature(sb.sidbe).parameters
    for option in dataclasses.fields(SidbeOptions):
        assert option.name in keywords, f"sb.sidbe lacks the option {option.name}"
        assert keywords[option.name].default == option.default or option.default is dataclasses.MISSING


def test_sidbe_takes_a_url_and_writes_plots(tmp_path):
    result = sb.sidbe("sim://", tmp_path / "run", **SHORT, max_iterations=1)
    assert result.verdict is sb.Verdict.PASS and len(result.iterations) == 1
    assert {p.name for p in result.plots} >= {"time.png", "friction.png"}
    assert result.model_file == tmp_path / "run" / "model.json" and result.model.source == str(result.model_file)


def test_identify_matches_the_cli(snippet, tmp_path, capsys):
    path = str(snippet.folder / "run" / "log.csv")
    cli = cli_json(capsys, "identify", path, "--json")
    assert sb.identify(path).to_dict() == cli
    assert sb.identify(sb.read_log(path)).to_dict() == cli
    joint = sb.identify(path, method="joint", out=tmp_path / "out")
    assert joint.to_dict() == cli_json(capsys, "identify", path, "--method", "joint", "--json")
    assert joint.source == str(tmp_path / "out" / "model.json")
    assert sb.load_model(joint.source) == joint and (tmp_path / "out" / "time.png").is_file()


def test_diagnose_matches_the_cli(snippet, tmp_path, capsys):
    path = str(snippet.folder / "run" / "log.csv")
    cli = cli_json(capsys, "diagnose", path, "--json")
    assert snippet.report.to_dict() == cli
    report = sb.diagnose(path, out=tmp_path / "d")
    assert report.to_dict() == cli and report.report == tmp_path / "d" / "report.md"
    saved = json.loads((tmp_path / "d" / "model.json").read_text())
    assert report.model.to_dict() == saved and report.model == sb.load_model(tmp_path / "d" / "model.json")
    assert report.headline.startswith("verdict: explained")


def test_validate_matches_the_cli(snippet, tmp_path, capsys):
    log = str(snippet.folder / "run" / "log.csv")
    model = str(snippet.model.save(tmp_path / "model.json"))
    cli = cli_json(capsys, "validate", model, log, "--json")
    assert sb.validate(model, log).to_dict() == cli
    assert sb.validate(sb.load_model(model), sb.read_log(log)).to_dict() == cli
    strict = sb.validate(model, log, min_fit_percent=100.0, out=tmp_path / "fig")
    cli = cli_json(capsys, "validate", model, log, "--min-fit", "100", "--out", str(tmp_path / "fig"), "--json",
                   status=3)  # fmt: skip
    assert strict.to_dict() == cli and strict.verdict is sb.Verdict.FAIL and not strict.passed
    assert strict.figure is not None and strict.figure.is_file()
    assert snippet.check.to_dict()["model"] is None  # a model made in Python names no file


def test_program_matches_the_cli(snippet, tmp_path, capsys):
    log = str(snippet.folder / "run" / "log.csv")
    model = str(snippet.model.save(tmp_path / "model.json"))
    cli = cli_json(capsys, "program", model, "--format", "json")
    assert sb.program(model).to_dict() == cli
    assert sb.program(sb.load_model(model)).to_dict() == cli
    argv = ["--fs", "500", "--log", log, "--phase-margin", "50", "--delay-cycles", "2", "--sign-band", "0.1"]
    cli = cli_json(capsys, "program", model, *argv, "--format", "json")
    api = sb.program(model, fs_hz=500, log=log, phase_margin_deg=50, delay_cycles=2, sign_band=0.1)
    assert api.to_dict() == cli
    sidbe_file = str(snippet.folder / "run" / "model.json")
    assert sb.program(sidbe_file).to_dict() == cli_json(capsys, "program", sidbe_file, "--format", "json")


# ------------------------------------------------------------------ models and their files
def test_model_round_trips_through_its_file(snippet, tmp_path, capsys):
    made = sb.Model(M=0.2, B=2.0, coulomb_pos=0.3, coulomb_neg=0.25, effects={"stribeck": {"fs": 0.5, "vs": 0.2}})
    assert made.delay is None and "delay_s" not in made.to_dict()
    for model in (snippet.model, snippet.report.model, snippet.result.model, made,
                  dataclasses.replace(made, delay=0.0), dataclasses.replace(snippet.model, M=0.3, delay=0.004)):  # fmt: skip
        path = model.save(tmp_path / "m.json")
        same = sb.load_model(path)
        assert same == model and same.to_dict() == model.to_dict() and same.source == str(path)
        assert same.delay == model.delay  # None stays None, 0 stays 0
        read = cli_json(capsys, "validate", str(path), str(snippet.folder / "run" / "log.csv"), "--json",
                        status=(0, 3))  # fmt: skip
        assert read["effects"] == list(model.effects)
    moved = dataclasses.replace(snippet.model, M=0.3).to_dict()
    assert moved["M"] == 0.3 and moved["pole"] == pytest.approx(-snippet.model.B / 0.3)
    assert moved["fit_percent"] == snippet.model.to_dict()["fit_percent"]  # the record is kept


def test_model_simulates_with_its_delay_and_effects(snippet):
    u = snippet.u
    plain = snippet.model.servo_model.simulate(u, 1000.0).v
    np.testing.assert_array_equal(snippet.model.simulate(u, fs=1000.0), plain)
    delayed = dataclasses.replace(snippet.model, delay=0.003)
    v = delayed.simulate(u, fs=1000.0)
    assert not np.allclose(v, plain)
    np.testing.assert_allclose(v[3:], plain[:-3], atol=1e-9)  # three whole cycles later
    as_effect = dataclasses.replace(snippet.model, delay=None, effects={"time_delay": {"delay": 0.003}})
    np.testing.assert_allclose(as_effect.simulate(u, fs=1000.0), v, atol=1e-9)


def test_log_is_the_log_type_everyone_reads(snippet):
    from servobench.bench.log.io import ExperimentLog

    log = snippet.log
    assert isinstance(log, ExperimentLog) and [r.run for r in log.runs] == [1, 2]
    assert isinstance(log.runs[0].t, np.ndarray) and log.fs_hz == 1000.0 and log.metadata["loop"] == "open"
    if importlib.util.find_spec("pandas") is None:
        with pytest.raises(ImportError, match="pip install pandas"):
            log.to_pandas()
        return
    frame = log.to_pandas()
    assert list(frame.columns[:5]) == ["run", "t", "u", "v", "x"]
    assert len(frame) == sum(len(r) for r in log.runs) and frame.attrs["fs_hz"] == 1000.0


# ------------------------------------------------------------------ drives and errors
def test_open_drive_stops_and_closes_on_an_error():
    with pytest.raises(RuntimeError, match="boom"), sb.open_drive("sim://") as drive:
        drive.enable()
        drive.command(0.5)
        raise RuntimeError("boom")
    assert not drive.is_open and not drive.enabled


def test_errors_are_servobench_errors_with_the_cli_message(snippet, tmp_path, capsys):
    missing = str(tmp_path / "missing.csv")
    with pytest.raises(sb.LogFormatError) as err:
        sb.read_log(missing)
    assert message(err.value) == cli_error(capsys, "identify", missing)
    with pytest.raises(sb.UsageError) as err:
        sb.load_model(tmp_path / "nope.json")
    assert message(err.value) == cli_error(capsys, "program", str(tmp_path / "nope.json"))
    with pytest.raises(sb.UsageError) as err:
        sb.sidbe("sim://", snippet.folder / "run")  # holds a run already
    assert message(err.value) == cli_error(capsys, "sidbe", "--drive", "sim://", "--out", str(snippet.folder / "run"))
    with pytest.raises(sb.UsageError) as err:
        sb.sidbe("sim://", tmp_path / "r", ratio=2.0)
    assert message(err.value) == cli_error(capsys, "sidbe", "--drive", "sim://", "--ratio", "2", "--out", str(tmp_path / "r"))
    with pytest.raises(sb.DriveUnavailableError) as err:
        sb.open_drive("nosuch://")
    assert message(err.value) == cli_error(capsys, "sidbe", "--drive", "nosuch://", "--out", str(tmp_path / "n"))
    with pytest.raises(sb.UsageError, match="states no loop rate"):
        sb.program(sb.Model(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4))
    with pytest.raises(sb.IdentificationError):
        sb.Model(M=-1.0, B=1.0, coulomb_pos=0.0, coulomb_neg=0.0)


def test_a_still_axis_raises_with_the_cli_note(tmp_path, capsys):
    url = "sim://?fc_pos=50&fc_neg=50"  # friction far above the command: the axis never moves
    with pytest.raises(sb.IdentificationError) as err:
        sb.sidbe(url, tmp_path / "api", **SHORT, max_iterations=1, plots=False)
    cli = cli_error(capsys, "sidbe", "--drive", url, *SHORT_CLI, "--max-iterations", "1", "--no-plots",
                    "--out", str(tmp_path / "cli"))  # fmt: skip
    assert message(err.value).endswith(f"no model.json written; the logs are kept in {tmp_path / 'api'}")
    assert message(err.value).replace(str(tmp_path / "api"), "DIR") == cli.replace(str(tmp_path / "cli"), "DIR")


# ------------------------------------------------------------------ commission and fleet
CONFIG = """
[limits]
max_u = 5.0
max_v = 20.0
xmin = -inf
xmax = inf

[sidbe]
periods = 3
period_s = 1.0
"""


@pytest.mark.slow
def test_commission_as_the_cli(tmp_path, capsys):
    config = tmp_path / "bench.toml"
    config.write_text(CONFIG)
    url = "sim://?pace=fast"
    result = sb.commission(url, config=config, out=tmp_path / "api", yes=True)
    assert result.status == "complete" and result.verdict is not None and result.verdict.passed
    assert result.to_dict() == json.loads((tmp_path / "api" / "commission.json").read_text())
    assert result.model == sb.load_model(tmp_path / "api" / "model.json")
    assert result.model.to_dict()["velocity_pi"]["kp"] > 0
    capsys.readouterr()
    assert main(["commission", "--drive", url, "--yes", "--config", str(config), "--out", str(tmp_path / "cli")]) == 0
    cli = json.loads((tmp_path / "cli" / "commission.json").read_text())
    assert set(result.to_dict()) == set(cli) and result.to_dict()["verdict"] == cli["verdict"]
    dry = sb.commission(url, config=config, out=tmp_path / "dry", yes=True, dry_run=True)
    assert dry.status == "dry-run" and dry.verdict is None and dry.model is None


@pytest.mark.slow
def test_fleet_as_the_cli(snippet, tmp_path, capsys):
    pytest.importorskip("distributed")
    pytest.importorskip("pyarrow")
    logs = str(snippet.folder / "run")
    result = sb.fleet(logs, tmp_path / "api", workers=1)
    assert len(result.rows) == 1 and not result.failed and result.page.is_file()
    cli = cli_json(capsys, "fleet", logs, "--out", str(tmp_path / "cli"), "--workers", "1", "--json")
    assert result.to_dict() == cli
