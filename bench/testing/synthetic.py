"""Synthetic SIDBE logs from the simulated plant, in memory (for tests and benchmarks).

:func:`simulate_experiment` produces what ``servobench run`` would log on a
``sim://`` drive with the same plant -- runs 1 (``u1``) and 2 (``u2``), each
starting at rest, with the excitation metadata -- without the file round trip.
"""

from __future__ import annotations

import numpy as np

from servobench.bench.log.io import ExperimentLog, RunData
from servobench.bench.procedure.excitation import ExcitationDesign, design_excitation
from servobench.sim_backend.physics.plant import Plant, PlantParams


def simulate_experiment(
    params: PlantParams,
    design: ExcitationDesign,
    rng: np.random.Generator | None = None,
    *,
    with_velocity: bool = True,
    with_position: bool = True,
) -> ExperimentLog:
    """Apply ``u1`` and ``u2`` of ``design`` to a plant at rest and return the log.

    Parameters
    ----------
    params : PlantParams
        Plant, including sensor noise (``noise``, ``noise_x``) and quantisation.
    design : ExcitationDesign
    rng : numpy.random.Generator, optional
        Noise source (default: seeded from ``params.seed``).
    with_velocity, with_position : bool
        Which feedback columns the log carries.
    """
    exc = design_excitation(design)
    plant = Plant(params, rng)
    runs = []
    dt = 1.0 / design.fs_hz
    for number, u in exc.runs():
        plant.reset()
        v, x = plant.step_block(u, dt)
        t = np.arange(len(u)) * dt
        runs.append(
            RunData(number, t, u.copy(), v if with_velocity else None, x if with_position else None)
        )
    meta = {k: _text(v) for k, v in design.metadata().items()}
    meta["loop"] = "open"
    return ExperimentLog(tuple(runs), meta, design.fs_hz, True, "synthetic")


def _text(value: object) -> str:
    if isinstance(value, (list, tuple)):
        return ",".join(format(float(v), ".10g") for v in value)
    return format(value, ".10g") if isinstance(value, float) else str(value)
