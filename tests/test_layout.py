"""Packaging and layout: one import name, every folder declared, a lazy CLI, a wheel that works alone."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
SETUPTOOLS = PYPROJECT["tool"]["setuptools"]
#: Folders with Python code that are deliberately not installed (test harnesses).
NOT_INSTALLED = {"servobench.bench.testing"}


def _packages_on_disk() -> set[str]:
    """Every package below the mapped folders, by its installed name."""
    found = set()
    for name, folder in SETUPTOOLS["package-dir"].items():
        root = REPO / folder
        for init in root.rglob("__init__.py"):
            rel = init.parent.relative_to(root)
            found.add(".".join((name, *rel.parts)))
    return found


def test_declared_packages_are_exactly_the_folders_on_disk():
    declared = set(SETUPTOOLS["packages"])
    on_disk = _packages_on_disk()
    assert declared == on_disk - NOT_INSTALLED, (
        f"not declared: {sorted(on_disk - NOT_INSTALLED - declared)}; "
        f"declared but missing: {sorted(declared - on_disk)}"
    )


def test_every_code_folder_is_a_package():
    """A folder of .py files without __init__.py would be left out of the wheel silently."""
    for folder in SETUPTOOLS["package-dir"].values():
        for py in (REPO / folder).rglob("*.py"):
            assert (py.parent / "__init__.py").exists(), f"{py.parent} has code but no __init__.py"


def test_one_top_level_name():
    assert {name.split(".")[0] for name in SETUPTOOLS["packages"]} == {"servobench"}
    assert PYPROJECT["project"]["scripts"]["servobench"].startswith("servobench.")


def _servobench_modules_after(code: str) -> set[str]:
    out = subprocess.run(
        [sys.executable, "-c", code + "\nimport sys\n"
         "print('\\n'.join(m for m in sys.modules if m.startswith('servobench')))"],
        capture_output=True, text=True, timeout=60, check=True,
    )  # fmt: skip
    return set(out.stdout.split())


def test_help_imports_no_subcommand():
    loaded = _servobench_modules_after(
        "import contextlib, io\nfrom servobench.bench.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    try:\n        main(['--help'])\n    except SystemExit:\n        pass"
    )
    assert "servobench.bench.cli" in loaded
    assert not {m for m in loaded if m.startswith("servobench.bench.commands.")}, loaded


def test_a_subcommand_imports_only_its_own_module():
    loaded = _servobench_modules_after(
        "import contextlib, io\nfrom servobench.bench.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    try:\n        main(['identify', '--help'])\n    except SystemExit:\n        pass"
    )
    commands = {m for m in loaded if m.startswith("servobench.bench.commands.")}
    assert "servobench.bench.commands.identify" in commands
    assert "servobench.bench.commands.sidbe" not in commands
    assert "servobench.drivers.canopen.drive" not in loaded


def test_a_served_base_plant_starts_without_the_effects_simulator():
    """``serve-sim`` of a plant without effects (the commonest served drive, started hundreds of
    times by the suite) loads neither the effects' compiled simulator nor numba; a plant with
    effects does."""
    code = (
        "import sys\nfrom servobench.sim_backend.servers.serve import device_from_url\n"
        "device_from_url({url!r}, wall_clock=True, clock_mode='real')\n"
        "print('numba' in sys.modules, 'servobench.sim_backend.physics.rich_plant' in sys.modules)"
    )
    for url, loaded in (("sim://?M=0.01&B=1", "False False"), ("sim://?backlash=0.01", "True True")):
        out = subprocess.run([sys.executable, "-c", code.format(url=url)], capture_output=True,
                             text=True, timeout=60, check=True)  # fmt: skip
        assert out.stdout.split() == loaded.split(), (url, out.stdout, out.stderr)


def test_cli_loads_where_grp_does_not_exist():
    code = (
        "import sys\nsys.modules['grp'] = None\n"
        "from servobench.bench.cli import main\n"
        "for argv in (['--help'], ['udev', '--help'], ['udev', 'install', '--help']):\n"
        "    try:\n        main(argv)\n    except SystemExit as e:\n        assert e.code == 0, (argv, e.code)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "usage: servobench udev install" in out.stdout


def test_no_arguments_prints_the_usage():
    out = subprocess.run(
        [sys.executable, "-m", "servobench"], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0
    assert out.stdout.startswith("usage: servobench")
    for command in ("sidbe", "identify", "diagnose", "commission"):
        assert command in out.stdout


def test_the_version_is_written_once():
    import servobench

    assert "version" in PYPROJECT["project"]["dynamic"]
    assert SETUPTOOLS["dynamic"]["version"] == {"attr": "servobench.__version__"}
    assert servobench.__version__.count(".") >= 1
    hits = [
        p for p in REPO.rglob("*.py")
        if ".venv" not in p.parts and p.parent.name != "tests"
        and "__version__ = " in p.read_text(encoding="utf-8")
    ]  # fmt: skip
    assert hits == [REPO / "servobench" / "__init__.py"]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    # Build from a copy of the tracked files: setuptools writes build/ beside the
    # sources, and the checkout must stay as it was.
    src = tmp_path_factory.mktemp("src")
    files = subprocess.run(
        ["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True
    ).stdout.decode().split("\0")
    for name in filter(None, files):
        if (REPO / name).is_file():
            (src / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / name, src / name)
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps",
         "--disable-pip-version-check", "-q", "-w", str(out), str(src)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert build.returncode == 0, build.stderr[-2000:]
    (path,) = out.glob("servobench-*.whl")
    return path


def test_wheel_holds_one_import_package_and_its_data(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names if not n.split("/")[0].endswith((".dist-info", ".data"))}
    assert top == {"servobench"}
    for needed in (
        "servobench/py.typed",
        "servobench/bench/cli.py",
        "servobench/drivers/data/cia402.eds",
        "servobench/drivers/data/maps/servobench-sim.toml",
        "servobench/drivers/data/dialects/odrive.toml",
        "servobench/udev/70-servobench-can.rules",
        "servobench/sim_backend/physics/plant.py",
    ):
        assert needed in names, needed
    assert not [n for n in names if n.startswith(("servobench/bench/testing/", "tests/", "benchmarks/"))]


def _site_packages(env_dir: Path) -> Path:
    """The purelib folder of the venv at ``env_dir``."""
    import sysconfig

    scheme = "nt_venv" if os.name == "nt" else "venv"
    if scheme not in sysconfig.get_scheme_names():  # Python < 3.11
        scheme = "nt" if os.name == "nt" else "posix_prefix"
    path = sysconfig.get_path("purelib", scheme, vars={"base": str(env_dir), "platbase": str(env_dir)})
    return Path(path)


@pytest.mark.slow
def test_installed_wheel_runs_outside_the_checkout(wheel, tmp_path):
    """The wheel alone, away from the checkout: the CLI works and ``import bench`` fails."""
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    # The new venv sees the running environment's dependencies, whether the suite runs in a venv
    # or in a bare interpreter: its site-packages folders as plain path lines. A path line does
    # not run the .pth files there, so an editable servobench (an import hook) stays out.
    (_site_packages(env_dir) / "running-environment.pth").write_text(
        "\n".join(p for p in sys.path if Path(p).name in ("site-packages", "dist-packages")) + "\n"
    )
    target = tmp_path / "site"
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "--disable-pip-version-check",
         "-q", "--target", str(target), str(wheel)],
        check=True, capture_output=True, timeout=300,
    )  # fmt: skip
    python = env_dir / ("Scripts" if os.name == "nt" else "bin") / "python"
    # The wheel's files come first on the path; the checkout is nowhere on it.
    env = {**os.environ, "PYTHONPATH": str(target)}
    work = tmp_path / "elsewhere"
    work.mkdir()

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [str(python), *args], cwd=work, env=env, capture_output=True, text=True, timeout=300
        )

    where = run("-c", "import servobench.bench.cli as c, rich; print(c.__file__)")
    assert where.returncode == 0, where.stderr
    assert Path(where.stdout.strip()).is_relative_to(target)
    checkout = run("-c", f"import sys; print(any(p.startswith({str(REPO)!r}) for p in sys.path))")
    assert checkout.stdout.strip() == "False", checkout.stderr
    for name in ("bench", "drivers", "sim_backend", "udev", "benchmarks"):
        gone = run("-c", f"import {name}")
        assert gone.returncode != 0 and "ModuleNotFoundError" in gone.stderr, name
    assert run("-m", "servobench", "--help").returncode == 0
    sidbe = run("-m", "servobench", "sidbe", "--drive", "sim://", "--json", "--out", str(work / "run"))
    assert sidbe.returncode == 0, sidbe.stderr[-2000:]
    assert '"pole"' in sidbe.stdout
    rules = run("-c", "from servobench.udev.rules import shipped_rules; print(len(shipped_rules()))")
    assert rules.stdout.strip() == "3", rules.stderr


def test_transport_folders_do_not_shadow_the_libraries_of_the_same_name():
    """``servobench.drivers.canopen`` and ``.serial`` sit beside the canopen and pyserial libraries.

    Every import is absolute, so a module inside ``drivers/canopen/`` that says ``import canopen``
    gets the library, not its own package; the same for ``serial``. Both orders of import are
    checked in fresh interpreters, and the library found is the one installed outside the folders.
    """
    code = (
        "import importlib, sys\n"
        "order = sys.argv[1:]\n"
        "for name in order:\n"
        "    importlib.import_module(name)\n"
        "import canopen, serial\n"
        "from servobench.drivers.canopen import link, sdo, session\n"
        "from servobench.drivers.serial import link as serial_link\n"
        "from servobench.sim_backend.servers.canopen import drive as served\n"
        "assert link.canopen is canopen and sdo.canopen is canopen and session.canopen is canopen\n"
        "assert served.canopen is canopen and serial_link.serial is serial\n"
        "assert canopen.BaseNode402 and canopen.Network, canopen\n"
        "assert serial.Serial and serial.SerialException, serial\n"
        "import servobench.drivers.canopen as ours_c, servobench.drivers.serial as ours_s\n"
        "assert ours_c is not canopen and ours_s is not serial\n"
        "print(canopen.__file__)\nprint(serial.__file__)\n"
    )
    for order in (
        ["canopen", "serial", "servobench.drivers.canopen.drive", "servobench.drivers.serial.drive"],
        ["servobench.drivers.canopen.drive", "servobench.drivers.serial.drive", "canopen", "serial"],
    ):
        out = subprocess.run(
            [sys.executable, "-c", code, *order], capture_output=True, text=True, timeout=120
        )
        assert out.returncode == 0, out.stderr[-2000:]
        for path in out.stdout.split():
            where = Path(path).resolve()
            assert not where.is_relative_to(REPO / "drivers"), where
            assert not where.is_relative_to(REPO / "sim_backend"), where
