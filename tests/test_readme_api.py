"""The README's Python API example runs as written, on the simulated drive, in a fresh folder."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


@pytest.mark.slow
def test_the_readme_python_example_runs(tmp_path, monkeypatch):
    block = re.search(r"## Python API.*?```python\n(.*?)```", README.read_text(encoding="utf-8"), re.S)
    assert block is not None, "the README lost its Python API example"
    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    exec(compile(block.group(1), "README.md", "exec"), scope)  # noqa: S102 - the documented example
    assert str(scope["result"].verdict.name) == "PASS"
    assert pytest.approx(0.1, rel=1e-6) == scope["model"].M and scope["same"] == scope["model"]
    assert scope["report"].verdict == "explained" and scope["check"].fit_percent > 99.9
    assert (tmp_path / "run" / "log.csv").exists() and (tmp_path / "model.json").exists()
