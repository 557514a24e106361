"""``servobench fleet`` on bad input: one line on stderr naming what to change, a non-zero exit."""

from __future__ import annotations

import socket

import pytest

from servobench.bench.cli import main


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]  # nothing listens once the socket is closed


@pytest.mark.parametrize(
    ("args", "status", "expect"),
    [
        (["{tmp}/nothing-here", "--out", "{tmp}/o"], 1, "no such log file or folder"),
        (["{tmp}", "--out", "{tmp}/o", "--workers", "0"], 1, "--workers must be >= 1"),
        (["{tmp}", "--out", "{tmp}/o", "--threshold", "-3"], 1, "--threshold must be a percentage > 0"),
        (["{tmp}", "--out", "{tmp}/o", "--workers", "2", "--scheduler", "tcp://x:1"], 2, "not allowed with"),
        (["{tmp}", "--out", "{tmp}/log.csv"], 1, "is a file; name a folder"),
        (["{tmp}", "--out", "{tmp}/o", "--scheduler", "tcp://127.0.0.1:{port}"], 1,
         "cannot reach the Dask scheduler at tcp://127.0.0.1:{port}"),
    ],
)  # fmt: skip
def test_bad_input_is_one_line_and_a_non_zero_exit(tmp_path, capsys, args, status, expect):
    (tmp_path / "log.csv").write_text("run,t,u,v\n1,0,0,0\n")
    port = _closed_port()
    argv = ["fleet", *(a.format(tmp=tmp_path, port=port) for a in args)]
    try:
        code = main(argv)
    except SystemExit as exit_:  # argparse
        code = exit_.code
    err = capsys.readouterr().err.strip()
    assert code == status
    assert expect.format(port=port) in err and len(err.splitlines()) == 1, err
    assert err.startswith("servobench: error:")
