"""``diagnose``, identification and ``sidbe`` run their solves on one BLAS thread and give the
user's setting back, also where the blocks nest."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
from threadpoolctl import threadpool_info, threadpool_limits

from servobench.bench.blas_threads import one_blas_thread
from servobench.bench.diagnose.workflow import diagnose
from servobench.bench.identify.auto import identify
from servobench.bench.log.io import ExperimentLog, RunData
from servobench.sim_backend.physics.plant import PlantParams, simulate


def _blas_threads() -> list[int]:
    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]


def test_one_blas_thread_inside_and_the_setting_restored_after():
    with threadpool_limits(limits=2, user_api="blas"):
        before = _blas_threads()
        assert before and max(before) == 2  # numpy's BLAS is loaded and set to 2
        with one_blas_thread():
            assert _blas_threads() == [1] * len(before)
        assert _blas_threads() == before


def _sidbe_log(seed: int, ratio: float) -> ExperimentLog:
    """Two runs of a switching command, the second ``ratio`` times the first, on a plant with friction."""
    fs, n = 500.0, 1500
    rng = np.random.default_rng(seed)
    runs = []
    for number in (1, 2):
        u = np.repeat(rng.choice([-2.0, 2.0], n // 50 + 1), 50)[:n] * (1.0 if number == 1 else ratio)
        v, x = simulate(u, fs, PlantParams(M=0.2, B=2.0, coulomb_pos=0.4, coulomb_neg=0.3), rng)
        runs.append(RunData(number, np.arange(n) / fs, u, v, x))
    return ExperimentLog(tuple(runs), {}, fs, True, "test")


def test_diagnose_runs_on_one_blas_thread():
    seen: list[list[int]] = []
    with threadpool_limits(limits=2, user_api="blas"):
        diagnose(_sidbe_log(3, 2.0), progress=lambda _m: seen.append(_blas_threads()))
        after = _blas_threads()
    assert seen and all(set(s) == {1} for s in seen)
    assert max(after) == 2


def test_nested_blocks_restore_only_at_the_outermost_exit():
    with threadpool_limits(limits=2, user_api="blas"):
        before = _blas_threads()
        with one_blas_thread():
            with one_blas_thread():
                pass
            assert _blas_threads() == [1] * len(before)  # the inner exit restored nothing
        assert _blas_threads() == before


def test_identification_runs_on_one_blas_thread(monkeypatch):
    import servobench.bench.identify.auto as auto

    seen: list[list[int]] = []
    original = auto._auto

    def spy(*args, **kwargs):
        seen.append(_blas_threads())
        return original(*args, **kwargs)

    monkeypatch.setattr(auto, "_auto", spy)
    with threadpool_limits(limits=2, user_api="blas"):
        result = identify(_sidbe_log(4, 0.9))
        after = _blas_threads()
    assert result.model.M > 0 and seen and all(set(s) == {1} for s in seen)
    assert max(after) == 2


def test_a_command_loads_openblas_with_one_thread_unless_the_user_set_it():
    """Numpy's and scipy's OpenBLAS threads cost a process 0.15-0.2 s of CPU as they start; a
    command's solves run on one thread anyway. The user's own setting is kept."""
    code = (
        "import contextlib, io\n"
        "from servobench.bench.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    main(['list', 'effects'])\n"
        "import scipy.linalg\n"
        "from threadpoolctl import threadpool_info\n"
        "print(max(p['num_threads'] for p in threadpool_info() if p['user_api'] == 'blas'))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    for setting, expected in ((None, 1), ("2", 2)):
        e = dict(env, **({"OPENBLAS_NUM_THREADS": setting} if setting else {}))
        out = subprocess.run([sys.executable, "-c", code], env=e, capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        assert int(out.stdout.strip().splitlines()[-1]) == expected
