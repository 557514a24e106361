"""Bad input gives one line on stderr, a non-zero exit and never a traceback."""

import subprocess
import sys

import pytest

CASES = {
    "missing file": ["identify", "{tmp}/nope.csv"],
    "malformed csv": ["identify", "{tmp}/bad.csv"],
    "ragged csv": ["identify", "{tmp}/ragged.csv"],
    "no-motion log": ["identify", "{tmp}/still.csv"],
    "sidbe on one run": ["identify", "{tmp}/still.csv", "--method", "sidbe"],
    "bad url scheme": ["sidbe", "--drive", "nosuch://x"],
    "bad url key": ["sidbe", "--drive", "sim://?bogus=1"],
    "amplitude > max_u": ["sidbe", "--drive", "sim://?max_u=1", "--amplitude", "2"],
    "ratio >= 1": ["sidbe", "--drive", "sim://", "--ratio", "1"],
    "fs = 0": ["sidbe", "--drive", "sim://", "--fs", "0"],
    "periods < 2": ["run", "--drive", "sim://", "--out", "{tmp}/x.csv", "--periods", "1"],
    "freq not commensurate": ["sidbe", "--drive", "sim://", "--freqs", "0.3,1"],
    "freq above nyquist": ["sidbe", "--drive", "sim://", "--freqs", "600"],
    "freqs not numbers": ["sidbe", "--drive", "sim://", "--freqs", "a,b"],
    "amplitude not a number": ["sidbe", "--drive", "sim://", "--amplitude", "x"],
}


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bad")
    (tmp / "bad.csv").write_text("# fs = 1000\nrun,t,u,v\n1,0,abc,0\n1,0.001,1,0\n")
    (tmp / "ragged.csv").write_text("run,t,u,v\n1,0,1,0\n1,0.001,1\n")
    rows = "\n".join(f"1,{k / 1000:.3f},{1.0 if k % 200 < 100 else -1.0},0,0" for k in range(2000))
    (tmp / "still.csv").write_text("# fs = 1000\nrun,t,u,v,x\n" + rows + "\n")
    return tmp


@pytest.mark.parametrize("name", list(CASES))
def test_bad_input_is_one_line_error(name, files):
    args = [a.format(tmp=files) for a in CASES[name]]
    p = subprocess.run(
        [sys.executable, "-m", "servobench", *args], capture_output=True, text=True, timeout=60
    )
    assert p.returncode != 0
    assert "Traceback" not in p.stderr
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, p.stderr
    assert lines[0].startswith("servobench: error")
    assert p.stdout == ""
