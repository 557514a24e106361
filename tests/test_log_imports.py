"""Logs from other tools: ';' and decimal commas, --columns, .mat files without a mapping.

The peer is the real EMPS record: converted the way a spreadsheet in a
decimal-comma locale exports it (Python's csv writer, ';', header names of
another tool), it must give exactly the model the original file gives.
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from servobench.bench.log.io import parse_log_text, read_log
from servobench.errors import LogFormatError

REPO = Path(__file__).resolve().parents[1]
EMPS = REPO.parent / "shared" / "data" / "emps"


def servobench(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "servobench", *args], capture_output=True, text=True, timeout=120
    )


@pytest.fixture(scope="module")
def spreadsheet_csv(tmp_path_factory) -> Path:
    """emps.csv as a German spreadsheet writes it: 'Zeit;Kraft;Position', '0,001'."""
    assert EMPS.is_dir(), f"EMPS data folder {EMPS} is absent (expected <repo>/../shared/data/emps)"
    log = read_log(EMPS / "emps.csv")
    run = log.runs[0]
    path = tmp_path_factory.mktemp("import") / "emps_de.csv"
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, delimiter=";", lineterminator="\r\n")
        w.writerow(["Zeit [s]", "Kraft [N]", "Position [m]"])
        for t, u, x in zip(run.t, run.u, run.x, strict=True):
            w.writerow([repr(float(v)).replace(".", ",") for v in (t, u, x)])
    return path


def test_semicolons_decimal_commas_and_other_names_give_the_original_model(spreadsheet_csv):
    before = servobench("identify", str(spreadsheet_csv), "--json")
    assert before.returncode == 1 and "lacks column(s) t, u" in before.stderr
    assert "--columns" in before.stderr  # the error says how to name them
    mapped = servobench(
        "identify", str(spreadsheet_csv), "--json", "--columns", "t=Zeit [s],u=Kraft [N],x=Position [m]"
    )
    assert mapped.returncode == 0, mapped.stderr
    original = servobench("identify", str(EMPS / "emps.csv"), "--json", "--loop", "closed")
    assert original.returncode == 0, original.stderr
    got, want = json.loads(mapped.stdout), json.loads(original.stdout)
    for key in ("M", "B", "coulomb_pos", "coulomb_neg"):
        assert got[key] == pytest.approx(want[key], rel=1e-9), key


def test_columns_on_diagnose_and_factors():
    text = "Time;Input;Speed\n" + "".join(
        f"{k / 1000:.3f};{'0,5' if k % 400 < 200 else '-0,5'};{(k % 7) / 10:.1f}\n".replace(".", ",")
        for k in range(100)
    )
    log = parse_log_text(text, columns="t=Time,u=Input*2,v=Speed")
    run = log.runs[0]
    assert set(run.extra) == set()  # mapped sources are not kept twice
    np.testing.assert_allclose(run.u[:3], [1.0, 1.0, 1.0])
    np.testing.assert_allclose(run.v[:8], [0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0])
    assert log.fs_hz == pytest.approx(1000.0)
    with pytest.raises(LogFormatError, match="no column 'Current' for u"):
        parse_log_text(text, columns="t=Time,u=Current,v=Speed")
    p = servobench("diagnose", "nope.csv", "--columns", "t=Time")
    assert p.returncode == 1 and "no such log file" in p.stderr  # the option exists on diagnose


def test_tab_separated_and_quoted_header():
    log = parse_log_text('"t"\t"u"\t"v"\n0\t1,5\t0\n0,01\t1,5\t0,2\n')
    np.testing.assert_allclose(log.runs[0].u, [1.5, 1.5])
    assert log.fs_hz == pytest.approx(100.0)


def test_mat_without_a_mapping_lists_its_variables():
    p = servobench("identify", str(EMPS / "DATA_EMPS.mat"))
    assert p.returncode == 1
    line = p.stderr.strip()
    assert len(line.splitlines()) == 1 and "Traceback" not in line
    for name in ("qm [", "vir [", "gtau (scalar)", "--mat-map"):
        assert name in line, line
    ok = servobench("identify", str(EMPS / "DATA_EMPS.mat"), "--columns", "t=t,u=vir*gtau,x=qm", "--json")
    assert ok.returncode == 0, ok.stderr
    assert json.loads(ok.stdout)["M"] == pytest.approx(95.1, rel=0.01)
