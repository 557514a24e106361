"""The real CLI on bad arguments: one line on stderr, a non-zero exit, never a traceback.

Every row runs ``python -m servobench.bench.cli ...`` in its own process; the processes
run concurrently (each one mostly imports), then each row is checked.
"""

from __future__ import annotations

import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import pytest


@dataclass(frozen=True)
class Row:
    """A bad command line; ``{tmp}`` in an argument is the test's folder."""

    name: str
    argv: tuple[str, ...]
    expect: str  # text the stderr line must contain
    status: int = 1  # 1: ServobenchError / OSError, 2: argparse usage


RUN = ("run", "--drive", "sim://", "--out", "{tmp}/log.csv")
ROWS = (
    Row("negative amplitude", (*RUN, "--amplitude", "-1"), "amplitude must be > 0"),
    Row(
        "amplitude over max_u",
        ("run", "--drive", "sim://?max_u=2", "--out", "{tmp}/l.csv", "--amplitude", "5"),
        "exceeds the drive limit max_u",
    ),  # fmt: skip
    Row("ratio of 1", (*RUN, "--ratio", "1"), "0 < ratio < 1"),
    Row("ratio above 1 (sidbe)", ("sidbe", "--drive", "sim://", "--ratio", "2"), "0 < ratio < 1"),
    Row("zero sample rate", (*RUN, "--fs", "0"), "fs must be > 0"),
    Row("amplitude not a number", (*RUN, "--amplitude", "abc"), "invalid float value", 2),
    Row("unknown transport", ("serve-sim", "--transport", "can-fd"), "invalid choice", 2),
    Row(
        "unknown URL scheme",
        ("run", "--drive", "profibus://x", "--out", "{tmp}/l.csv"),
        "unknown drive scheme 'profibus'",
    ),  # fmt: skip
    Row(
        "output folder under a file",
        ("run", "--drive", "sim://", "--out", "{tmp}/file/sub/l.csv"),
        "file",
    ),  # fmt: skip
    Row("not a URL", ("run", "--drive", "notaurl", "--out", "{tmp}/l.csv"), "not a drive URL"),
    Row(
        "unknown query key",
        ("run", "--drive", "sim://?M=1&bogus=1", "--out", "{tmp}/l.csv"),
        "does not take query key(s) bogus",
    ),  # fmt: skip
    Row(
        "malformed number in URL",
        ("run", "--drive", "sim://?M=abc", "--out", "{tmp}/l.csv"),
        "is not a number",
    ),  # fmt: skip
    Row(
        "canopen URL without node",
        ("run", "--drive", "canopen://vcan0", "--out", "{tmp}/l.csv"),
        "needs node=1..127",
    ),  # fmt: skip
    Row(
        "nothing listening",
        ("run", "--drive", "modbus+tcp://127.0.0.1:1?map=servobench-sim", "--out", "{tmp}/l.csv"),
        "cannot connect",
    ),  # fmt: skip
    Row("missing log (identify)", ("identify", "{tmp}/missing.csv"), "no such log file"),
    Row("missing log (diagnose)", ("diagnose", "{tmp}/missing.csv"), "no such log file"),
    Row("log that is no log", ("identify", "{tmp}/file"), "header lacks column(s) t, u"),
    Row(
        "bad fault spec",
        ("serve-sim", "--transport", "modbus-tcp", "--fault", "crc@3"),
        "crc applies to modbus-rtu only",
    ),  # fmt: skip
    Row(
        "state file in a missing folder",
        ("serve-sim", "--transport", "serial", "--state-file", "{tmp}/none/state.json"),
        "No such file",
    ),  # fmt: skip
)
#: The progress bar must not draw (an empty stderr line) when the run fails before its first sample.
OUTPUT_FILE_IS_A_FOLDER = Row(
    "output folder is a file", ("run", "--drive", "sim://", "--out", "{tmp}/file/l.csv"),
    "Not a directory",
)  # fmt: skip


def run_cli(row: Row, tmp: Path) -> subprocess.CompletedProcess[str]:
    argv = [a.replace("{tmp}", str(tmp)) for a in row.argv]
    env = {**os.environ, "COLUMNS": "200", "PYTHONWARNINGS": "ignore"}
    return subprocess.run(
        [sys.executable, "-m", "servobench", *argv],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
        stdin=subprocess.DEVNULL,
    )


@pytest.fixture(scope="module")
def results(tmp_path_factory: pytest.TempPathFactory) -> dict[str, subprocess.CompletedProcess]:
    tmp = tmp_path_factory.mktemp("cli")
    (tmp / "file").write_text("not a log\n")
    rows = (*ROWS, OUTPUT_FILE_IS_A_FOLDER)
    with ThreadPoolExecutor(max_workers=4) as pool:
        done = pool.map(lambda r: run_cli(r, tmp), rows)
        return {row.name: proc for row, proc in zip(rows, done, strict=True)}


def check(row: Row, proc: subprocess.CompletedProcess) -> None:
    assert proc.returncode == row.status, (proc.returncode, proc.stderr)
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 1, f"stderr is not one line: {proc.stderr!r}"
    assert lines[0].startswith("servobench: error: ") and row.expect in lines[0], lines[0]


@pytest.mark.parametrize("row", ROWS, ids=lambda r: r.name)
def test_bad_arguments_give_one_line_and_a_non_zero_exit(row: Row, results) -> None:
    check(row, results[row.name])


def test_output_path_under_a_file(results) -> None:
    check(OUTPUT_FILE_IS_A_FOLDER, results[OUTPUT_FILE_IS_A_FOLDER.name])
