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

from servobench.bench.diagnose.data import REFIT_MAX_SAMPLES, DiagnosisData
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


def windows(data: DiagnosisData, fit: bool = False) -> list[Window]:
    """Every comparison window of the data (``fit``: every fitting window), in order."""
    out = []
    every = data.fit_starts if fit else data.starts
    for i, (r, starts) in enumerate(zip(data.segments, every, strict=True)):
        ends = np.append(starts[1:], len(r))
        out.extend((i, int(s), int(e)) for s, e in zip(starts, ends, strict=True))
    return out


def thinned(chosen: list[Window], samples: int) -> list[Window]:
    """An evenly spread subset of ``chosen`` holding about ``samples`` samples."""
    total = sum(e - s for _, s, e in chosen)
    if total > samples and len(chosen) > 1:
        keep = max(1, int(len(chosen) * samples / total))
        idx = np.unique(np.linspace(0, len(chosen) - 1, keep).round().astype(int))
        chosen = [chosen[i] for i in idx]
    return chosen


def held_out_windows(data: DiagnosisData) -> list[Window]:
    """Fitting windows that hold held-out samples, thinned to about REFIT_MAX_SAMPLES (all of
    them for whole-run simulation of a short log): where quick scores are judged."""
    chosen = [w for w in windows(data, fit=True) if data.held_out[w[0]][w[1] : w[2]].any()]
    return thinned(chosen, REFIT_MAX_SAMPLES)


def simulate(
    data: DiagnosisData,
    cand: Candidate,
    which: Sequence[Window] | None = None,
    added: Sequence[np.ndarray] | None = None,
) -> list[np.ndarray]:
    """Simulated velocity per run (NaN outside the windows simulated).

    ``added`` holds, per run, a force [command units] added to the logged command (the
    sensitivity of the simulation to a force, :mod:`.verdict`).

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
        u = r.u if added is None else r.u + added[i]
        state = PlantState(initial_velocity(r, sigma, s), float(r.position[s]))
        if model is None:
            v, _, _ = simulate_coulomb(u[s:e], dt, params, state)
        else:
            model.reset()
            model.prime(u[:s], dt)
            v, _, _ = model.simulate(u[s:e], dt, state)
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
