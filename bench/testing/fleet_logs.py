"""Generated fleets of SIDBE logs on disk (for the fleet tests and benchmark).

:func:`write_fleet` writes, for each axis, several dated records of a short
SIDBE experiment on the simulated plant (:func:`simulate_experiment`), with
the ``axis`` and ``time`` metadata the runner writes. An axis may wear: its
Coulomb levels and viscous friction grow from record to record, as a
fatigued screw's do.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np

from servobench.bench.log.io import ExperimentLog, LogWriter
from servobench.bench.procedure.excitation import make_design
from servobench.bench.testing.synthetic import simulate_experiment
from servobench.sim_backend.physics.plant import PlantParams

#: First record of every axis.
START = datetime(2026, 1, 5, 8, 0, tzinfo=timezone(timedelta(hours=1)))
#: Days between two records of an axis.
INTERVAL_DAYS = 30


@dataclass(frozen=True)
class AxisSpec:
    """An axis of a generated fleet.

    Attributes
    ----------
    name : str
    records : int
        Dated records (one SIDBE log each).
    wear : float
        Growth of ``coulomb_pos``, ``coulomb_neg`` and ``B`` from the first to the
        last record, as a fraction (0.5: +50 %), linear in the record index.
    plant : PlantParams
        The axis when new.
    """

    name: str
    records: int = 3
    wear: float = 0.0
    plant: PlantParams = PlantParams(noise=0.002)


def write_log(log: ExperimentLog, path: Path, metadata: Mapping[str, object] = ()) -> Path:
    """Write ``log`` as a servobench CSV log (``run,t,u,v,x``) with extra ``metadata``."""
    meta = {"fs": log.fs_hz, **log.metadata, **dict(metadata)}
    with LogWriter(path, meta) as writer:
        for r in log.runs:
            writer.append_block(np.full(len(r), r.run), r.t, r.u, r.v, r.x)
    return path


def record_plant(spec: AxisSpec, index: int, seed: int) -> PlantParams:
    """The plant of record ``index`` of ``spec`` (worn by ``index/(records-1)`` of its wear)."""
    share = index / max(1, spec.records - 1)
    grow = 1.0 + spec.wear * share
    p = spec.plant
    return p.with_changes(
        B=p.B * grow, coulomb_pos=p.coulomb_pos * grow, coulomb_neg=p.coulomb_neg * grow, seed=seed
    )


def write_fleet(
    folder: Path,
    axes: Sequence[AxisSpec],
    *,
    amplitude: float = 2.0,
    period_s: float = 1.0,
    periods: int = 3,
) -> list[Path]:
    """Write every record of ``axes`` under ``folder/<axis>/<date>.csv``; the paths, in order.

    Records are dated :data:`START` + ``i`` x :data:`INTERVAL_DAYS`; seeds differ per log.
    """
    design = make_design(amplitude, periods=periods, period_s=period_s)
    paths: list[Path] = []
    seed = 1
    for spec in axes:
        (folder / spec.name).mkdir(parents=True, exist_ok=True)
        for i in range(spec.records):
            when = START + timedelta(days=INTERVAL_DAYS * i)
            log = simulate_experiment(record_plant(spec, i, seed), design)
            path = folder / spec.name / f"{when:%Y-%m-%d}.csv"
            write_log(log, path, {"axis": spec.name, "time": when.isoformat(), "unit_u": "N m",
                                  "unit_v": "rad/s", "unit_x": "rad"})  # fmt: skip
            paths.append(path)
            seed += 1
    return paths
