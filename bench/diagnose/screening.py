"""Look for each library effect's signature in what the current model leaves unexplained.

Builds the :class:`~servobench.sim_backend.physics.effects.spec.ScreenInput` (low-passed
velocity, acceleration and command, the residual of the current model) and
asks every effect module's ``screen`` for a score, a parameter guess and an
evidence sentence. A quick simulation of each guess then ranks the candidates
on held-out data before any costly refit.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from servobench.bench.diagnose.data import DiagnosisData
from servobench.bench.diagnose.simulate import Candidate, gap_percent, held_out_windows, simulate
from servobench.bench.identify.derivative import filter_command
from servobench.errors import UsageError
from servobench.sim_backend.physics import effects as library
from servobench.sim_backend.physics.effects.spec import RunSignals, Screening, ScreenInput

#: Samples whose low-passed speed is below this fraction of its rms are left out of the
#: inverse-dynamics equation (friction is undetermined at rest).
MOVING_FRACTION = 0.05
#: Couplings that exclude each other.
EXCLUSIVE = ({"resonance", "backlash"},)
#: Library terms fitted with an effect as part of it. A Stribeck curve's static level may
#: differ by direction as the Coulomb levels do (a breakaway excess added to each
#: direction's level), where the library's ``stribeck`` holds one static level: a constant
#: force beside it reaches the rest, since below the Coulomb levels an offset only shifts
#: them. The pair is one Stribeck curve with a static level per direction, named
#: ``stribeck``; without it the curve's fit stops short and a second effect soaks up the rest.
COMPANIONS = {"stribeck": "offset"}


def with_companion(
    name: str, base: dict[str, float], effects: dict[str, dict[str, float]]
) -> tuple[dict[str, float], dict[str, dict[str, float]]]:
    """``(base, effects)`` with the companion of effect ``name`` added (when it has one, not
    yet in the model): the Coulomb levels made equal and their difference carried by the
    constant force, as the screening's curve has one excess over both levels."""
    c = COMPANIONS.get(name)
    if c is None or c in effects:
        return base, effects
    p, n = float(base["coulomb_pos"]), float(base["coulomb_neg"])
    m = 0.5 * (p + n)
    return {**base, "coulomb_pos": m, "coulomb_neg": m}, {**effects, c: {"offset": 0.5 * (n - p)}}


def companion_bounds(name: str, cand: Candidate) -> dict[str, dict[str, tuple[float, float]]]:
    """Refit bounds of the companion of ``name`` in ``cand``: a force up to the Coulomb
    level (beyond it the axis would drift: an offset of its own)."""
    c = COMPANIONS.get(name)
    if c is None or c not in cand.effects:
        return {}
    top = max(float(cand.base["coulomb_pos"]), float(cand.base["coulomb_neg"]), 1e-9)
    return {c: {"offset": (-top, top)}}


def without(effects: dict, name: str, keep: Iterable[str] = ()) -> dict:
    """``effects`` without ``name`` and its companion (unless the companion is in ``keep``:
    named for itself)."""
    c = COMPANIONS.get(name)
    return {k: v for k, v in effects.items() if k != name and (k != c or c in keep)}


def screen_input(data: DiagnosisData, cand: Candidate, v_sim: Sequence[np.ndarray]) -> ScreenInput:
    """Screening signals of every run given the current model's simulated velocity."""
    fs = data.fs_hz

    def command_filter(u: np.ndarray) -> np.ndarray:
        return filter_command(u, fs)

    runs = []
    for r, vs in zip(data.segments, v_sim, strict=True):
        v_f = r.v_f
        a_f = np.gradient(v_f, data.dt_s)
        u_f = command_filter(r.u)
        vs = np.where(np.isfinite(vs), vs, r.v)
        runs.append(RunSignals(r.u, r.v, r.position, v_f, a_f, u_f, r.v - vs, vs))
    v_all = np.concatenate([s.v_f for s in runs])
    rms = float(np.sqrt(np.mean(v_all**2)))
    moving = np.abs(v_all) > MOVING_FRACTION * rms
    return ScreenInput(
        tuple(runs),
        data.dt_s,
        dict(cand.base),
        dict(cand.effects),
        moving,
        command_filter,
        np.concatenate(data.held_out),
    )


def compatible(name: str, present: Iterable[str]) -> bool:
    present = set(present)
    if name in present:
        return False
    return not any(name in group and present & (group - {name}) for group in EXCLUSIVE)


def screen_all(
    ctx: ScreenInput, present: Iterable[str], effects: Iterable[str] | None = None
) -> dict[str, Screening]:
    """Screening of every library effect (of ``effects``, default all) not yet in the model
    and compatible with it."""
    present = tuple(present)
    allowed = library.names() if effects is None else tuple(effects)
    out = {}
    for name in library.names():
        if name in allowed and compatible(name, present):
            try:
                out[name] = library.module(name).screen(ctx)
            except (ValueError, ZeroDivisionError, FloatingPointError):
                continue  # its signature cannot be read from this log (an axis mostly at rest)
    return out


@dataclass(frozen=True)
class QuickScore:
    """Held-out gap [%] of the best screening guess, and where refits should start.

    ``starts`` holds the best candidate built on the screening's main guess; the main guess
    on the other base too when the two bases are far apart (:func:`unsettled`, nearer for a
    rugged effect: the quick simulation cannot tell which basin the refit will reach); when
    the screening offered alternatives, the best of those (rugged surfaces: each is
    refitted); and when it offered
    restarts (starts with a base of their own), the best of those too, whatever its quick gap
    (its guess of the term was made on the current base: the refit moves both).
    """

    name: str
    held_out_gap: float
    starts: tuple[Candidate, ...]


#: Two bases are far apart when B or a Coulomb level differs by more than this factor.
BASE_SPREAD = 2.0
#: ... or by more than this one, for an effect whose screening asks its refit to scan (a rugged
#: surface): there a quick simulation of the guess on the wrong base says nothing of the basin
#: its refit reaches (cogging wells 1.9 times the Coulomb level: on the current base, its
#: friction 1.5 times the joint fit's, the guess simulated better and its refit missed the
#: wells; from the joint base, whose guess simulated worse, it reached them).
RUGGED_SPREAD = 1.25


def unsettled(a: dict[str, float], b: dict[str, float], spread: float = BASE_SPREAD) -> bool:
    """Whether bases ``a`` and ``b`` differ by more than ``spread`` in ``B`` or in
    the mean Coulomb level: a current base whose best linear-plus-Coulomb fit wanted ``B < 0``
    (a strong Stribeck curve) against the screening's joint fit with ``B`` held positive."""
    for pair in (
        (a["B"], b["B"]),
        (a["coulomb_pos"] + a["coulomb_neg"], b["coulomb_pos"] + b["coulomb_neg"]),
    ):
        lo, hi = sorted(abs(float(x)) for x in pair)
        if hi > spread * lo:
            return True
    return False


def quick_score(data: DiagnosisData, current: Candidate, name: str, s: Screening) -> QuickScore:
    """Simulate the guesses with the current base, and the main guess with the jointly fitted
    base too; keep the best main-guess candidate, the other main one when the bases are far
    apart, the best alternative and the best restart."""
    trials = [(dict(current.base), dict(s.guess), "main")]
    if s.base is not None and all(np.isfinite(list(s.base.values()))):
        b = dict(s.base)
        if b["M"] > 0 and b["B"] > 0:
            b = {
                **b,
                "coulomb_pos": max(b["coulomb_pos"], 0.0),
                "coulomb_neg": max(b["coulomb_neg"], 0.0),
            }
            trials.append((b, dict(s.guess), "joint"))
    trials += [(dict(current.base), dict(g), "alternative") for g in s.alternatives]
    trials += [(dict(b), dict(g), "restart") for b, g in s.restarts]
    which = held_out_windows(data)
    best: dict[str, tuple[float, Candidate]] = {}
    for base, guess, kind in trials:
        base, effects = with_companion(name, base, {**current.effects, name: guess})
        effects[name] = library.project(name, effects[name], base)
        cand = Candidate(base, effects)
        try:
            gap = gap_percent(data, simulate(data, cand, which), "held_out")
        except UsageError:
            continue
        if np.isfinite(gap) and (kind not in best or gap < best[kind][0]):
            best[kind] = (gap, cand)
    if not best:
        fallback = Candidate(dict(current.base), {**current.effects, name: dict(s.guess)})
        return QuickScore(name, float("inf"), (fallback,))
    mains = sorted((best[k] for k in ("main", "joint") if k in best), key=lambda item: item[0])
    kept = mains[:1]
    spread = RUGGED_SPREAD if s.scan else BASE_SPREAD
    if len(mains) == 2 and unsettled(dict(mains[0][1].base), dict(mains[1][1].base), spread):
        kept.append(mains[1])
    kept += [best[k] for k in ("alternative", "restart") if k in best]
    ranked = sorted(kept, key=lambda item: item[0])
    return QuickScore(name, ranked[0][0], tuple(c for _, c in ranked))
