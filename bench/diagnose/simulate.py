"""Simulate a candidate model on the log and measure the gap.

A :class:`Candidate` is the base model (``M, B, coulomb_pos, coulomb_neg``) plus an
ordered set of effects; it runs on the same simulator the ``sim://`` drive
uses (:mod:`servobench.sim_backend.physics.coulomb` for the base, :mod:`servobench.sim_backend.physics.rich_plant`
with effects), so what diagnose names can be simulated back.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from servobench.bench.diagnose.data import DiagnosisData
from servobench.bench.identify.dataset import initial_velocity
from servobench.sim_backend.physics.coulomb import PlantParams, PlantState, simulate_coulomb
from servobench.sim_backend.physics.rich_plant import build_model

BASE_KEYS = ("M", "B", "coulomb_pos", "coulomb_neg")


@dataclass(frozen=True)
class Candidate:
    """Base parameters and effects ``{name: {parameter: value}}`` in the order they were added."""

    base: Mapping[str, float]
    effects: Mapping[str, Mapping[str, float]] = field(default_factory=dict)

    def plant(self) -> PlantParams:
        b = self.base
        return PlantParams(
            M=float(b["M"]),
            B=float(b["B"]),
            coulomb_pos=max(float(b["coulomb_pos"]), 0.0),  # a fit may step below zero
            coulomb_neg=max(float(b["coulomb_neg"]), 0.0),
            effects={k: dict(v) for k, v in self.effects.items()},
        )

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.effects)


Window = tuple[int, int, int]  # run index, first sample, end sample (exclusive)


def windows(data: DiagnosisData) -> list[Window]:
    """Every comparison window of the data, in order."""
    out = []
    for i, (r, starts) in enumerate(zip(data.segments, data.starts, strict=True)):
        ends = np.append(starts[1:], len(r))
        out.extend((i, int(s), int(e)) for s, e in zip(starts, ends, strict=True))
    return out


def held_out_windows(data: DiagnosisData) -> list[Window]:
    """Windows that hold held-out samples (all of them for whole-run simulation)."""
    return [w for w in windows(data) if data.held_out[w[0]][w[1] : w[2]].any()]


def simulate(
    data: DiagnosisData, cand: Candidate, which: Sequence[Window] | None = None
) -> list[np.ndarray]:
    """Simulated velocity per run (NaN outside the windows simulated).

    Raises
    ------
    UsageError
        Parameters the simulator rejects (e.g. a Stribeck level below Coulomb).
    """
    params = cand.plant()
    model = build_model(params) if params.effects else None
    dt = data.dt_s
    sigma = data.sigma_v
    out = [np.full(len(r), np.nan) for r in data.segments]
    for i, s, e in windows(data) if which is None else which:
        r = data.segments[i]
        state = PlantState(initial_velocity(r, sigma, s), float(r.position[s]))
        if model is None:
            v, _, _ = simulate_coulomb(r.u[s:e], dt, params, state)
        else:
            model.reset()
            model.prime(r.u[:s], dt)
            v, _, _ = model.simulate(r.u[s:e], dt, state)
        out[i][s:e] = v
    return out


def gap_percent(data: DiagnosisData, v_sim: Sequence[np.ndarray], part: str = "all") -> float:
    """NRMSE [%] of simulated against measured velocity: ``100 rms(error) / std(measured)``.

    ``part`` is ``"all"``, ``"held_out"`` or ``"train"``; samples not simulated are skipped.
    """
    err, meas = [], []
    for r, held, vs in zip(data.segments, data.held_out, v_sim, strict=True):
        mask = np.isfinite(vs)
        if part == "held_out":
            mask &= held
        elif part == "train":
            mask &= ~held
        err.append(vs[mask] - r.v[mask])
        meas.append(r.v[mask])
    e, m = np.concatenate(err), np.concatenate(meas)
    if e.size == 0 or not np.std(m) > 0:
        return float("nan")
    return float(100.0 * np.sqrt(np.mean(e * e)) / np.std(m))


def base_as_dict(values: Mapping[str, float]) -> dict[str, float]:
    return {k: float(values[k]) for k in BASE_KEYS}
