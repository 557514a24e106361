"""examples/identify_sim.ipynb runs: its code cells, in order, as a kernel would run them.

The cells are executed with a plain ``exec`` in one namespace, in a fresh folder, with
matplotlib's Agg backend: no Jupyter is needed (the notebook uses no magics).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

NOTEBOOK = Path(__file__).resolve().parents[1] / "examples" / "identify_sim.ipynb"


def _notebook() -> dict:
    return json.loads(NOTEBOOK.read_text(encoding="utf-8"))


def _code_cells() -> list[str]:
    return ["".join(c["source"]) for c in _notebook()["cells"] if c["cell_type"] == "code"]


def test_the_notebook_is_kept_clean():
    """Committed without outputs, so that a diff shows code, not images."""
    nb = _notebook()
    assert nb["nbformat"] == 4 and nb["metadata"]["kernelspec"]["language"] == "python"
    code = [c for c in nb["cells"] if c["cell_type"] == "code"]
    assert code and all(c["outputs"] == [] and c["execution_count"] is None for c in code)
    assert not any(
        line.lstrip().startswith(("%", "!")) for src in _code_cells() for line in src.splitlines()
    )


@pytest.mark.slow
def test_the_notebook_identifies_the_simulated_drive_and_plots_it(tmp_path, monkeypatch):
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    monkeypatch.chdir(tmp_path)
    plt.close("all")
    scope: dict = {"__name__": "__main__"}
    for n, source in enumerate(_code_cells()):
        exec(compile(source, f"identify_sim.ipynb, code cell {n + 1}", "exec"), scope)  # noqa: S102
    try:
        model, plant = scope["model"], scope["PLANT"]
        for name, true in plant.items():
            assert getattr(model, name) == pytest.approx(true, rel=0.02), name
        assert scope["check"].fit_percent > 90
        # measured against simulated, in each figure
        figures = [plt.figure(n) for n in plt.get_fignums()]
        assert len(figures) == 2
        for fig in figures:
            labels = {line.get_label() for ax in fig.axes for line in ax.get_lines()}
            assert "measured" in labels and any(label.startswith("simulated") for label in labels)
        assert (tmp_path / "servobench-runs").is_dir()
    finally:
        plt.close("all")
