"""The session's set-up: peers installed first, a worker per core, the files marked ``slow`` first.

The package's bytecode is cached (``__pycache__``, as Python does by default) even where the
machine sets ``PYTHONDONTWRITEBYTECODE``: the tests start hundreds of Python processes. They
load OpenBLAS with one thread, as the CLI's commands do, unless the environment says otherwise.

Before any test runs, the controller makes the peers the selected tests pair
with present (:mod:`peers`: installed as root, else one line and a non-zero
exit), and compiles the plant simulator's kernels into numba's cache in a
process of its own (:data:`WARM_KERNELS`): a first compile holds the GIL for
seconds, which in a test streaming to a drive would starve its watchdog feeder.

The suite runs with one test file per worker (``--dist loadfile`` in
pyproject.toml). ``-n auto`` gives a worker per core, and one more when the
machine is idle as the suite starts: about a third of the suite's time is
spent waiting on wall-clock time (drives streaming in real time at their
rate, watchdogs, time-outs), and on an idle machine a third worker fills
those waits; on a busy one it would only add contention, so there it is not
started. The workers take files in collection order (xdist's reordering by
number of tests is off), so a slow file collected last would run alone at
the end while the other workers sit idle: the slow files start first and the
short ones fill in around them.

A test that judges a model's accuracy on a served drive streaming in real time
takes :func:`realtime_bench` first: one such bench at a time across the
workers. A bench machine runs one real-time host, its cyclic thread at
SCHED_FIFO pinned to one core; two at once on two cores pin two such threads
(and two real-time drives spinning on their byte times) to the same
processors, which no bench does. Other work, time-shared, runs beside it.
"""

from __future__ import annotations

import fcntl
import os
import subprocess
import sys
from collections.abc import Iterator

import peers
import psutil
import pytest

from servobench.bench.cli import BLAS_THREADS

#: Share of all cores busy [%], measured over :data:`IDLE_PROBE_S` as the suite starts, below
#: which the machine counts as idle and ``-n auto`` starts one worker more than it has cores.
IDLE_BELOW_PERCENT = 25.0
IDLE_PROBE_S = 0.5


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    cores = len(os.sched_getaffinity(0))
    busy = psutil.cpu_percent(interval=IDLE_PROBE_S)
    return cores + 1 if busy < IDLE_BELOW_PERCENT else cores


#: Run once by the controller: every kernel of the compiled simulator compiled and cached.
WARM_KERNELS = """
import numpy as np
from servobench.bench.testing.hidden_effects import random_case
from servobench.sim_backend.physics import effects
from servobench.sim_backend.physics.coulomb import PlantState
from servobench.sim_backend.physics.effects.backlash import engaged
from servobench.sim_backend.physics.rich_plant import build_model
rng = np.random.default_rng(0)
u = np.sign(np.sin(np.arange(400) * 0.05))
for effect in (None, *effects.names()):
    build_model(random_case(effect, rng).params).simulate(u, 1e-3, PlantState(0.0, 0.0))
engaged(np.cumsum(u) * 1e-3, 0.01)
from servobench.bench.identify.pair_placement import _allowed_pair_errors, _alone, _place_alone, _posterior, _viterbi
from servobench.bench.identify.simulation import simulate_variable_dt
from servobench.sim_backend.physics.coulomb import PlantParams
simulate_variable_dt(u, np.full(u.size - 1, 1e-3), PlantParams(), 0.0)
_viterbi(np.arange(4.0)[:, None] + np.array([-1.0, 0.0]), np.ones((4, 2), bool), np.zeros((3, 2, 2)),
         np.array([-1.0, 0.0]), 1.0)
_place_alone(np.array([1]), np.arange(3.0), np.zeros(3), np.full(3, 2.0), u[:3], u[:3], 1e-3, 0.01, 1.0, 0.5,
             0.4, 0.5, 0.4)
_allowed_pair_errors(np.arange(3.0)[:, None], np.ones((3, 1), bool), u[:3], u[:2], u[:2], 1e-3, PlantParams())
_posterior(np.arange(4.0)[:, None] + np.array([-1.0, 0.0]), np.ones((4, 2), bool), np.zeros((3, 2, 2)),
           np.array([-1.0, 0.0]), 1.0, 2.0, rng)
_alone(np.array([1]), np.arange(3.0), np.zeros(3), np.full(3, 2.0), u[:3], u[:3], 1e-3, 0.01, 1.0, 0.5, 0.4,
       0.5, 0.4, 2.0, np.full(1, 0.5))
from servobench.bench.identify.derivative import lowpass
lowpass(np.cumsum(u), 1000.0)
"""


def pytest_configure(config: pytest.Config) -> None:
    peers.check(config)  # the controller only; a worker returns at once
    if not hasattr(config, "workerinput"):
        # the hundreds of Python processes the tests start read the package's bytecode from
        # __pycache__ (ignored by git) rather than compile every module each time; a machine
        # that sets PYTHONDONTWRITEBYTECODE would have each compile it anew (measured: 4.5 % of
        # the suite's CPU). Set before the workers start, so they and their children inherit it.
        os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
        sys.dont_write_bytecode = False
        # the workers, the served drives and every other Python child load OpenBLAS with one
        # thread, as the CLI's commands do (bench.cli.BLAS_THREADS): the threads two OpenBLAS
        # builds start at load cost each process 0.15-0.2 s of CPU, and the suite starts hundreds
        for name, value in BLAS_THREADS.items():
            os.environ.setdefault(name, value)
        subprocess.run([sys.executable, "-c", WARM_KERNELS], check=True, timeout=600)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    slow_files = {item.path for item in items if item.get_closest_marker("slow") is not None}
    items.sort(key=lambda item: item.path not in slow_files)  # stable: order kept within each


@pytest.fixture
def realtime_bench(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Held while the test streams to a served drive in real time: one such test at a time over
    all workers (a lock file in the session's shared temporary folder; see the module doc)."""
    root = tmp_path_factory.getbasetemp()
    root = root.parent if root.name.startswith("popen-gw") else root
    with open(root / "realtime-bench.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
