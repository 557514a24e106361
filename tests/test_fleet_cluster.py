"""``servobench fleet`` on real Dask clusters: a LocalCluster of 2 processes and a
``dask scheduler`` with two ``dask worker`` processes started here on loopback.

The fleet is generated from the simulated plant: three axes of three dated
SIDBE records each, one of them wearing (Coulomb levels and B +50 % from the
first record to the last), a log without axis/time metadata, and a corrupt
log. Each run must give the same rows as a plain sequential loop, report the
corrupt log, flag the worn axis (with a drift near the plant's true +50 %)
and not the unworn controls. One scheduler serves the whole module.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import psutil
import pyarrow.csv as pacsv
import pyarrow.parquet as pq
import pytest

from servobench.bench.fleet.engine import run_sequential
from servobench.bench.fleet.sources import find_logs
from servobench.bench.fleet.table import COLUMNS
from servobench.bench.log.identity import parse_time
from servobench.bench.procedure.excitation import make_design
from servobench.bench.testing.fleet_logs import AxisSpec, write_fleet, write_log
from servobench.bench.testing.synthetic import simulate_experiment
from servobench.sim_backend.physics.plant import PlantParams

pytestmark = pytest.mark.slow  # clusters start in seconds

WEAR = 0.5
STRINGS = ("log", "axis", "time", "method", "effects", "error", "model")
CLI = [sys.executable, "-m", "servobench"]
#: Longest wait for the scheduler and its workers to come up [s].
START_S = 90.0


@pytest.fixture(scope="module")
def fleet(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("fleet") / "logs"
    write_fleet(root, [AxisSpec("worn", wear=WEAR), AxisSpec("control"), AxisSpec("steady")])
    legacy = write_log(simulate_experiment(PlantParams(noise=0.002, seed=99), make_design(
        2.0, periods=3, period_s=1.0)), root / "legacy-7.csv")  # fmt: skip
    os.utime(legacy, (1767225600, 1767225600))  # 2026-01-01 00:00 UTC, no axis/time lines
    good = (root / "steady" / "2026-01-05.csv").read_text().splitlines()
    (root / "steady" / "corrupt.csv").write_text("\n".join(good[:40] + ["1,0.5,nan?,0,0"]) + "\n")
    return root


@pytest.fixture(scope="module")
def sequential(fleet) -> list[dict]:
    return [r.record() for r in run_sequential(find_logs([fleet]))]


@pytest.fixture(scope="module")
def scheduler(tmp_path_factory):
    """``dask scheduler`` and two ``dask worker`` processes on 127.0.0.1; its address."""
    folder = tmp_path_factory.mktemp("dask")
    file = folder / "scheduler.json"
    dask = [sys.executable, "-m", "dask"]
    common = ["--no-dashboard", "--host", "127.0.0.1"]
    procs = [subprocess.Popen(
        [*dask, "scheduler", *common, "--port", "0", "--scheduler-file", str(file),
         "--idle-timeout", "600"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=folder,
    )]  # fmt: skip
    try:
        deadline = time.monotonic() + START_S
        while not file.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert file.exists(), "dask scheduler did not start"
        for _ in range(2):
            procs.append(subprocess.Popen(
                [*dask, "worker", "--scheduler-file", str(file), *common, "--nworkers", "1",
                 "--nthreads", "1", "--death-timeout", "60", "--local-directory", str(folder)],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=folder,
            ))  # fmt: skip
        address = json.loads(file.read_text())["address"]
        _wait_for_workers(address, 2)
        yield address
    finally:
        _shutdown(file)
        for p in reversed(procs):
            if p.poll() is None:
                p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def _shutdown(file: Path) -> None:
    """Ask the scheduler to stop itself and its workers (faster than a signal to each)."""
    from distributed import Client

    try:
        with Client(scheduler_file=str(file), timeout=10, set_as_default=False) as client:
            client.shutdown()
    except Exception:  # noqa: BLE001 -- not started, or gone already: the signals follow
        pass
    time.sleep(0.5)


def _wait_for_workers(address: str, n: int) -> None:
    from distributed import Client

    with Client(address, timeout=START_S, set_as_default=False) as client:
        client.wait_for_workers(n, timeout=START_S)
        assert len(client.scheduler_info()["workers"]) == n


def _fleet(*args: str, timeout: float = 240) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, "fleet", *args], capture_output=True, text=True, timeout=timeout)


def _read_csv(path: Path) -> list[dict]:
    options = pacsv.ConvertOptions(
        column_types={c: "string" for c in STRINGS}, strings_can_be_null=False
    )
    table = pacsv.read_csv(path, convert_options=options)
    assert table.column_names == list(COLUMNS)
    return table.to_pylist()


def _check_tables(done: subprocess.CompletedProcess, out: Path, sequential: list[dict]) -> None:
    assert done.returncode == 1, done.stderr  # one log failed
    assert "Traceback" not in done.stderr
    assert "identifying 11 logs" in done.stderr  # the progress bar
    assert _read_csv(out / "fleet.csv") == sequential
    assert pq.read_table(out / "fleet.parquet").to_pylist() == sequential
    failed = [r for r in sequential if r["error"]]
    assert [Path(r["log"]).name for r in failed] == ["corrupt.csv"]
    assert "malformed number" in failed[0]["error"]


def _check_json(report: dict) -> None:
    assert report["logs"] == 11 and report["failed"] == 1
    axes = {a["axis"]: a for a in report["axes"]}
    assert sorted(axes) == ["control", "legacy-7", "steady", "worn"]
    worn = axes["worn"]
    assert worn["flagged"] and worn["records"] == 3
    for p in ("coulomb_pos", "coulomb_neg", "B"):
        assert worn["drift"][p] == pytest.approx(100 * WEAR, abs=2.0)
        assert any(reason.startswith(f"{p} +") for reason in worn["reasons"])
    for name in ("control", "steady", "legacy-7"):
        assert not axes[name]["flagged"] and axes[name]["reasons"] == []
        assert abs(axes[name]["drift"]["coulomb_pos"]) < 2.0
    assert axes["steady"]["records"] == 3  # the corrupt log is not a record
    when = parse_time(axes["legacy-7"]["first"])  # from the file's modification time
    assert when == datetime(2026, 1, 1, tzinfo=timezone.utc)
    assert axes["worn"]["units"]["coulomb_pos"] == "N m"


@pytest.mark.parametrize(("workers", "where"), [("2", "scheduler tcp://127.0.0.1:"), ("1", "in this process")])
def test_local_cluster_gives_the_sequential_rows(fleet, sequential, tmp_path, workers, where):
    """Two worker processes, or one worker inside the fleet's own process (no process started)."""
    out = tmp_path / "out"
    done = _fleet(str(fleet), "--out", str(out), "--workers", workers, "--json")
    assert f"11 logs on {workers} Dask workers ({where}" in done.stderr
    _check_tables(done, out, sequential)
    _check_json(json.loads(done.stdout))


def test_dask_scheduler_and_workers_give_the_sequential_rows(
    fleet, sequential, scheduler, tmp_path
):
    out = tmp_path / "out"
    done = _fleet(str(fleet), "--out", str(out), "--scheduler", scheduler)
    _check_tables(done, out, sequential)
    lines = done.stdout.splitlines()
    assert lines[0] == "11 logs, 1 failed; 4 axes, 1 flagged"
    assert [line.split(":")[0] for line in lines[1:3]] == [
        "FLAGGED worn",
        "failed " + str(fleet / "steady" / "corrupt.csv"),
    ]
    page = (out / "trend.html").read_text()
    assert page.count("<img ") == 5  # the overview and one per axis
    assert "FLAGGED: coulomb_pos +" in page and "corrupt.csv" in page


def test_diagnose_flags_an_effect_the_first_record_lacked(scheduler, tmp_path):
    design = make_design(2.0, periods=3, period_s=1.0, fs_hz=250.0)
    cogging = {"cogging": {"amp": 0.4, "period": 0.1, "phase": 0.3}}
    logs = tmp_path / "logs"
    logs.mkdir()
    for axis, effects in (("new-cogging", cogging), ("control", {})):
        for day, eff in ((1, {}), (2, effects)):
            log = simulate_experiment(PlantParams(noise=0.002, seed=day, effects=eff), design)
            write_log(
                log, logs / f"{axis}-{day}.csv", {"axis": axis, "time": f"2026-04-0{day}T10:00:00"}
            )
    out = tmp_path / "out"
    done = _fleet(str(logs), "--out", str(out), "--scheduler", scheduler, "--diagnose", "--json")
    assert done.returncode == 0, done.stderr
    axes = {a["axis"]: a for a in json.loads(done.stdout)["axes"]}
    assert axes["new-cogging"]["flagged"] and not axes["control"]["flagged"]
    assert any("effect cogging appeared" in r for r in axes["new-cogging"]["reasons"])
    rows = _read_csv(out / "fleet.csv")
    assert [r["effects"] for r in rows] == [
        "",
        "",
        "",
        "cogging",
    ]  # sorted: control-1, control-2, new-1, new-2
    assert all(r["gap_before"] is not None and r["gap_after"] is not None for r in rows)
    assert rows[3]["gap_after"] < rows[3]["gap_before"] / 4


#: Runs argv[1:] with SIGINT unblocked and at its default action, as a terminal's foreground job.
FOREGROUND = (
    "import os, signal, sys; signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT}); "
    "signal.signal(signal.SIGINT, signal.SIG_DFL); os.execv(sys.argv[1], sys.argv[1:])"
)


def test_ctrl_c_shuts_the_local_cluster_down_and_keeps_the_rows(fleet, tmp_path):
    logs = tmp_path / "logs"
    for i in range(16):
        shutil.copytree(fleet / "worn", logs / f"copy{i}")
    out = tmp_path / "out"
    cmd = [*CLI, "fleet", str(logs), "--out", str(out), "--workers", "2", "--json"]
    # started as a terminal's foreground job is, Ctrl-C at its default action: a suite started in
    # a shell's background ignores SIGINT (seen: the xdist workers under pytest 9.2), and a child
    # inherits that, as nohup means it to (the fleet then rightly runs to its end)
    foreground = [sys.executable, "-c", FOREGROUND, *cmd]
    proc = subprocess.Popen(foreground, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)  # fmt: skip
    try:
        started = proc.stderr.readline()  # the cluster is up: "... logs on 2 Dask workers ..."
        assert "48 logs on 2 Dask workers" in started, started + proc.stderr.read()
        family = psutil.Process(proc.pid).children(recursive=True)
        time.sleep(0.5)
        os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C in a terminal does: the whole group
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, stderr
    assert "interrupted; Dask cluster shut down" in stderr and "Traceback" not in stderr
    last = stderr.strip().splitlines()[-1]
    assert json.loads(stdout)["error"] == last.removeprefix("servobench: ")  # one object
    rows = _read_csv(out / "fleet.csv")
    assert len(rows) == 48
    assert all(r["error"] in ("", "not processed: interrupted (Ctrl-C)") for r in rows)
    assert any(r["error"] for r in rows)  # the interrupt stopped the work mid-way
    deadline = time.monotonic() + 15
    while any(p.is_running() and p.status() != psutil.STATUS_ZOMBIE for p in family):
        assert time.monotonic() < deadline, "Dask processes left running after Ctrl-C"
        time.sleep(0.2)
