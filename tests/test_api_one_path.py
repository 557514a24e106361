"""The CLI is a thin layer over the public API (issue 31): one path, not two.

The dependency points one way: the API (``servobench/*.py``) and the library below it never
import the command line (``servobench.bench.commands``, ``servobench.bench.cli``); each main
command parses its arguments, calls the API function of the same name and prints what it
returns, so its output is the API's ``to_dict()`` for the same input, whatever the log is
called and however its columns are named.
"""

from __future__ import annotations

import ast
import json
import shutil
from pathlib import Path

import pytest

import servobench as sb
from servobench.bench.cli import main

#: The checkout's folders that install as servobench.* (bench/ is servobench.bench ...).
ROOT = Path(__file__).resolve().parents[1]
#: The command line (and ``python -m servobench``, its entry): only it may import it.
CLI_MODULES = ("servobench.bench.commands", "servobench.bench.cli", "servobench.__main__")
#: The main commands, the API function each one calls, and arguments that parse.
COMMANDS = {
    "sidbe": ("servobench.procedures", ["--drive", "sim://"]),
    "identify": ("servobench.analysis", ["log.csv"]),
    "diagnose": ("servobench.analysis", ["log.csv"]),
    "validate": ("servobench.analysis", ["model.json", "log.csv"]),
    "program": ("servobench.analysis", ["model.json"]),
    "commission": ("servobench.procedures", ["--drive", "sim://", "--dry-run"]),
    "fleet": ("servobench.procedures", ["log.csv", "--out", "fleet"]),
}
#: What a command must not do itself: the orchestration the API function runs.
ORCHESTRATION = {
    "servobench.bench.procedure.sidbe": {"run_sidbe", "check_run_folder"},
    "servobench.bench.procedure.run_folder": {"check_run_folder", "default_out_dir"},
    "servobench.bench.identify.auto": {"identify"},
    "servobench.bench.diagnose.workflow": {"diagnose"},
    "servobench.bench.model.validate": {"validate", "judge"},
    "servobench.bench.model.program": {"design_values", "DriveScale"},
    "servobench.bench.model.file": {"read_model", "program_model"},
    "servobench.bench.log.io": {"read_log"},
    "servobench.bench.commission.sequence": {"commission", "CommissionOptions"},
    "servobench.bench.fleet.engine": {"connect", "run_on", "map_on"},
    "servobench.bench.fleet.sources": {"find_logs"},
    "servobench.bench.fleet.table": {"write_csv", "write_parquet"},
    "servobench.bench.fleet.page": {"write_page"},
}


def _module_name(path: Path) -> str:
    """``servobench.<...>`` of a file of the checkout (``bench/x.py`` is ``servobench.bench.x``)."""
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[0] != "servobench":
        parts.insert(0, "servobench")
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(path: Path) -> set[tuple[str, str]]:
    """Every ``(module, name)`` the file imports, anywhere in it (``name`` "" for ``import m``),
    relative imports resolved."""
    module = _module_name(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: set[tuple[str, str]] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update((alias.name, "") for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{up}.{base}" if base else up
            found.update((base, alias.name) for alias in node.names)
    return found


def _library_files() -> list[Path]:
    """The installed package's files outside the command line (the API and every layer below)."""
    folders = ("servobench", "bench", "drivers", "sim_backend", "udev")
    files = [p for folder in folders for p in (ROOT / folder).rglob("*.py")]
    return [p for p in files if not _module_name(p).startswith(CLI_MODULES)]


def _reaches_cli(module: str, name: str) -> bool:
    target = f"{module}.{name}" if name else module
    return any(target == m or target.startswith(m + ".") for m in CLI_MODULES)


def test_the_api_and_the_library_never_import_the_command_line():
    files = _library_files()
    assert any(p.parent.name == "servobench" and p.name == "procedures.py" for p in files)
    wrong = sorted(
        f"{p.relative_to(ROOT)} imports {m}{'.' + n if n else ''}"
        for p in files
        for m, n in _imports(p)
        if _reaches_cli(m, n)
    )
    assert not wrong, "the dependency must point from the CLI to the API, never back:\n" + "\n".join(wrong)


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_the_command_does_not_run_the_procedure_itself(command):
    imported = _imports(ROOT / "bench" / "commands" / f"{command}.py")
    api = COMMANDS[command][0]
    assert (api, command) in imported, f"servobench {command} does not call {api}.{command}"
    wrong = sorted(f"{m}.{n}" for m, n in imported if n in ORCHESTRATION.get(m, ()))
    assert not wrong, f"servobench {command} runs {wrong} itself, beside the API"


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_the_command_calls_the_api_function(command, monkeypatch, capsys):
    import importlib

    module, argv = COMMANDS[command]
    called = []

    def stub(*args, **kwargs):
        called.append((args, kwargs))
        raise sb.UsageError(f"{command} went through the API")

    monkeypatch.setattr(importlib.import_module(module), command, stub)
    capsys.readouterr()
    assert main([command, *argv]) == 1
    assert capsys.readouterr().err == f"servobench: error: {command} went through the API\n"
    assert len(called) == 1


# ------------------------------------------------------------------ the same output, however the log is named
@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """A run on sim:// with, beside its log, a copy whose columns another tool named."""
    where = tmp_path_factory.mktemp("one-path")
    result = sb.sidbe("sim://", where / "run", periods=2, period_s=2.0, max_iterations=1, plots=False)
    lines = result.log.resolve().read_text(encoding="utf-8").splitlines()
    header = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    lines[header] = lines[header].replace("run,t,u,v,x", "run,Time,Input,Velocity,Position")
    (where / "renamed.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    shutil.copyfile(result.model_file, where / "model.json")
    return where


MAP = "t=Time,u=Input,v=Velocity,x=Position"


def _cli_json(capsys, *argv: str, status: tuple[int, ...] = (0,)) -> dict:
    capsys.readouterr()
    rc = main(list(argv))
    out, err = capsys.readouterr()
    assert rc in status, err
    return json.loads(out)


def test_identify_diagnose_validate_read_the_columns_and_name_the_log_as_given(folder, monkeypatch, capsys):
    monkeypatch.chdir(folder)
    log = "./renamed.csv"  # named as the user typed it, not as the path normalises it
    cli = _cli_json(capsys, "identify", log, "--columns", MAP, "--json")
    api = sb.identify(log, columns=MAP)
    assert api.to_dict() == cli and cli["log"] == log
    assert api == sb.identify("run/log.csv")  # the same samples under other column names
    assert api.details is not None and api.details.fit_percent == pytest.approx(cli["fit_percent"])

    cli = _cli_json(capsys, "validate", "./model.json", log, "--mat-map", MAP, "--json")
    check = sb.validate("./model.json", log, mat_map=MAP)
    assert check.to_dict() == cli and (cli["model"], cli["log"]) == ("./model.json", log)
    assert check.model == sb.load_model("model.json") and check.details.fit_percent == check.fit_percent
    assert check.headline.startswith(f"PASS: ./model.json on {log}: ")

    cli = _cli_json(capsys, "diagnose", log, "--columns", MAP, "--json")
    report = sb.diagnose(log, columns=MAP)
    assert report.to_dict() == cli and report.details.verdict.verdict == report.verdict


def test_program_names_the_scale_log_as_given(folder, monkeypatch, capsys):
    monkeypatch.chdir(folder)
    cli = _cli_json(capsys, "program", "./model.json", "--log", "./run/log.csv", "--format", "json")
    assert sb.program("./model.json", log="./run/log.csv").to_dict() == cli and cli["model"] == "./model.json"


def test_the_text_output_leads_with_the_api_headline(folder, monkeypatch, capsys):
    monkeypatch.chdir(folder)
    capsys.readouterr()
    assert main(["validate", "model.json", "run/log.csv"]) == 0
    assert capsys.readouterr().out.splitlines()[0] == sb.validate("model.json", "run/log.csv").headline
    capsys.readouterr()
    assert main(["diagnose", "run/log.csv"]) == 0
    assert capsys.readouterr().out.splitlines()[0] == sb.diagnose("run/log.csv").headline
