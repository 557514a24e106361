"""``servobench sidbe --json`` in a child process, as a user runs it, into a folder that goes after.

The tests judge the main job by what it prints and writes: :func:`sidbe_json` gives the exit
status, the standard output (the model's JSON), the tail of the standard error and the ``#``
header of every log the run wrote, by file name (``log.csv``, ``log-1.csv``,
``hold-trial.csv``, ...).
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

#: Characters of the standard error kept (its end: the one line an error gives is last).
STDERR_KEPT = 4000


def sidbe_json(url: str, args: Sequence[str] = (), timeout_s: float = 600.0) -> dict:
    """``servobench sidbe --drive url --json --out FOLDER *args`` in a temporary folder.

    Returns
    -------
    dict
        ``rc`` (exit status), ``stdout``, ``stderr`` (its last :data:`STDERR_KEPT`
        characters) and ``heads``: ``{file name: its header lines}`` of each CSV the run wrote.
    """
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "run"
        proc = subprocess.run(
            [sys.executable, "-m", "servobench", "sidbe", "--drive", url, "--json", "--out", str(run), *args],
            capture_output=True, text=True, timeout=timeout_s,
        )  # fmt: skip
        heads = {
            path.name: "".join(
                line for line in path.read_text(encoding="utf-8").splitlines(keepends=True)
                if line.startswith("#")
            )
            for path in sorted(run.glob("*.csv"))
        }  # fmt: skip
    return {"rc": proc.returncode, "stdout": proc.stdout, "stderr": proc.stderr[-STDERR_KEPT:], "heads": heads}
