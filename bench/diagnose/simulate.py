"""Simulate a candidate model on the log and measure the gap.

A :class:`Candidate` is the base model (``M, B, coulomb_pos, coulomb_neg``) plus an
ordered set of effects; it runs on the same simulator the ``sim://`` drive
uses (:mod:`servobench.sim_backend.physics.coulomb` for the base, :mod:`servobench.sim_backend.physics.rich_plant`
with effects), so what diagnose names can be simulated back: compiled
(:mod:`servobench.sim_backend.physics.compiled`), every window of every candidate of a batch
in one call (:func:`simulate_many`: a Jacobian's columns), the reference loops for a model
whose terms are not all data.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from servobench.bench.diagnose.data import REFIT_MAX_SAMPLES, DiagnosisData
from servobench.bench.identify.dataset import initial_velocity
from servobench.errors import UsageError
from servobench.sim_backend.physics.compiled import pack_coulomb, run
from servobench.sim_backend.physics.coulomb import PlantParams, PlantState
from servobench.sim_backend.physics.rich_plant import RichModel, build_model

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
    (out,) = simulate_many(data, [cand], which, added)
    if isinstance(out, UsageError):
        raise out
    return out


def simulate_many(
    data: DiagnosisData,
    cands: Sequence[Candidate],
    which: Sequence[Window] | None = None,
    added: Sequence[np.ndarray] | None = None,
) -> list[list[np.ndarray] | UsageError]:
    """:func:`simulate` of each candidate, the compiled ones in one call; the error instead
    of the velocity for parameters the simulator rejects."""
    which = windows(data) if which is None else list(which)
    out: list = []
    for flat in simulate_flat(data, cands, which, added):
        if isinstance(flat, UsageError):
            out.append(flat)
            continue
        per_run = [np.full(len(r), np.nan) for r in data.segments]
        col = 0
        for i, s, e in which:
            per_run[i][s:e] = flat[col : col + e - s]
            col += e - s
        out.append(per_run)
    return out


def simulate_flat(
    data: DiagnosisData,
    cands: Sequence[Candidate],
    which: Sequence[Window],
    added: Sequence[np.ndarray] | None = None,
    start_dv: float = 0.0,
) -> list[np.ndarray | UsageError]:
    """:func:`simulate_many`'s velocities as one array per candidate: the windows ``which``, each
    after the one before it (what a fit compares, without the runs' arrays around them).

    ``start_dv`` [units/s] is added to the measured velocity each window starts from where the
    axis moves there (not where it starts at rest): the sensitivity of the simulation to the
    noise of that sample (:mod:`.sigma`)."""
    dt = data.dt_s
    sigma = data.sigma_v
    u_runs = [r.u if added is None else r.u + added[i] for i, r in enumerate(data.segments)]
    rows, start, col = [], [], 0  # per window: run, first sample, samples, output column
    for i, s, e in which:
        r = data.segments[i]
        v0, x0 = initial_velocity(r, sigma, s), float(r.position[s])
        if start_dv and v0 != 0.0:
            v0 += start_dv
        rows.append((i, s, e - s, col))
        start.append((v0, x0, v0, x0, 0.0))
        col += e - s
    carry = continues(which)
    out: list = [None] * len(cands)
    packs, lines, batch = [], [], []
    shared: dict[
        int, list[np.ndarray]
    ] = {}  # delay [samples] -> lines of models without transforms
    for c, cand in enumerate(cands):
        try:
            params = cand.plant()
            model = build_model(params) if params.effects else None
            pk = pack_coulomb(params, dt) if model is None else model.packed(dt)
        except UsageError as err:
            out[c] = err
            continue
        if pk is None:
            try:
                per_run = _reference(data, model, which, u_runs, start, carry)
                out[c] = np.concatenate([per_run[i][s:e] for i, s, e in which])
            except UsageError as err:
                out[c] = err
            continue
        if pk.inputs:
            lines.append([pk.line(u) for u in u_runs])
        else:
            lines.append(shared.setdefault(pk.whole, [pk.line(u) for u in u_runs]))
        packs.append(pk)
        batch.append(c)
    if packs:
        v, _, _ = run(packs, lines, np.array(rows, dtype=np.int64).reshape(-1, 4), np.array(start), carry)
        for p, c in enumerate(batch):
            out[c] = v[p]
    return out


def continues(which: Sequence[Window]) -> np.ndarray:
    """Per window: it starts where the window before it ended, in the same run. There the
    simulation restarts the measured body at the measured state and carries on what no sensor
    sees (a play's engaged side and load, a spring's twist): restarting those relaxed every
    0.5 s of a closed-loop log left a play's true model a 24.8 % gap where the whole run
    simulated gives 0.97 % (diagnose_cases.py #164)."""
    out = np.zeros(len(which), dtype=bool)
    for w in range(1, len(which)):
        out[w] = which[w][0] == which[w - 1][0] and which[w][1] == which[w - 1][2]
    return out


def _reference(
    data: DiagnosisData,
    model: RichModel,
    which: Sequence[Window],
    u_runs: Sequence[np.ndarray],
    start: Sequence[tuple],
    carry: np.ndarray,
) -> list[np.ndarray]:
    """A model whose terms are not all data, window by window on the reference loops."""
    out = [np.full(len(r), np.nan) for r in data.segments]
    for w, ((i, s, e), (v0, x0, *_)) in enumerate(zip(which, start, strict=True)):
        u = u_runs[i]
        if carry[w]:
            model.carry_on(PlantState(v0, x0))
        else:
            model.reset()
        model.prime(u[:s], data.dt_s)
        v, _, _ = model.simulate(u[s:e], data.dt_s, PlantState(v0, x0))
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
