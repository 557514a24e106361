"""The real EMPS data set must reproduce the published IDIM-LS reference (Janot et al. 2019)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from servobench.bench.identify.auto import identify
from servobench.bench.log.io import read_log

REPO = Path(__file__).resolve().parents[1]
EMPS = REPO.parent / "shared" / "data" / "emps"

# published: M = 95.1089, Fv = 203.5034, Fc = 20.3935, offset = -3.1648 (tau = ... + Fc sign(qd) + offset)
M_REF, B_REF = 95.1089, 203.5034
FC_POS_REF = 20.3935 + (-3.1648)  # friction force when moving forward: Fc + offset
FC_NEG_REF = 20.3935 - (-3.1648)  # magnitude when moving backward: Fc - offset

pytestmark = pytest.mark.skipif(
    not EMPS.is_dir(),
    reason=f"EMPS data folder {EMPS} is absent (expected <repo>/../shared/data/emps)",
)


def _check(out):
    assert out["M"] == pytest.approx(M_REF, rel=0.01)
    assert out["B"] == pytest.approx(B_REF, rel=0.03)
    assert out["coulomb_pos"] == pytest.approx(FC_POS_REF, rel=0.05)
    assert out["coulomb_neg"] == pytest.approx(FC_NEG_REF, rel=0.05)


def test_emps_csv_through_the_cli():
    p = subprocess.run(
        [sys.executable, "-m", "servobench", "identify", str(EMPS / "emps.csv"), "--json"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    _check(out)
    assert out["method"] == "joint" and "sidbe cannot run" in out["selection"]
    assert out["fit_percent"] > 90.0


def test_emps_mat_with_variable_map():
    log = read_log(EMPS / "DATA_EMPS.mat", mat_map="t=t,u=vir*gtau,x=qm")
    _check(identify(log).to_json())
