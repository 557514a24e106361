"""Steps 4-5: rank candidate effects, refit combinations, keep what pays on held-out data.

Each round screens every library effect against the current model's residual
(signature score and a quick simulation of the guess), refits the most
promising single additions and the pairs among them, and compares them on
held-out samples. Pairs compete with singles so that two wrong terms that
together mimic one missing effect (viscous plus drag for a Stribeck curve)
do not win by greed: a pair is taken only when it beats the best single
clearly, a single only when it beats the current model clearly. The loop
stops when nothing pays, or when the model reaches the sensor-noise floor.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

from bench.diagnose.data import DiagnosisData, noise_floor_percent
from bench.diagnose.refit import FitResult, evaluate, refit
from bench.diagnose.screening import compatible, quick_score, screen_all, screen_input
from bench.diagnose.simulate import Candidate
from sim_backend.effects.spec import Screening

#: Relative held-out improvement a term (or a pair over a single) must bring.
MIN_GAIN = 0.15
#: Singles refitted per round: the best quick guesses that beat the current model, and
#: the best screening scores of at least MIN_SCORE.
TOP_BY_QUICK = 2
TOP_BY_SCORE = 3
MIN_SCORE = 0.05
#: Singles whose pairs are refitted.
PAIR_POOL = 3
#: Rounds of additions.
MAX_ROUNDS = 3
#: A gap within this factor of the noise floor leaves nothing to explain.
FLOOR_FACTOR = 1.25
#: Pairs are tried only when the best single leaves more than this share of the
#: unexplained (above-noise) residual energy.
PAIR_BELOW = 0.8


@dataclass(frozen=True)
class Step:
    """One accepted addition (or the base model, with ``added == ()``)."""

    added: tuple[str, ...]
    fit: FitResult
    evidence: dict[str, str]


@dataclass(frozen=True)
class SearchTrace:
    """What each round tried: ``(names, held-out gap [%])`` per refitted candidate."""

    rounds: tuple[tuple[tuple[tuple[str, ...], float], ...], ...]
    noise_floor: float


def _explained(before: FitResult, after: FitResult, floor: float) -> float:
    """Share of the above-noise held-out residual energy that ``after`` removes."""
    room = before.gap_held_out**2 - floor**2
    if room <= 0:
        return 1.0
    return (before.gap_held_out**2 - after.gap_held_out**2) / room


def _ablate(
    data: DiagnosisData, chosen: tuple[str, ...], fit: FitResult
) -> tuple[tuple[str, ...], FitResult]:
    """Drop new terms the fitted model does not need (it does as well on held-out data without)."""
    kept = chosen
    for name in chosen:
        cand = fit.candidate
        without = Candidate(dict(cand.base), {k: v for k, v in cand.effects.items() if k != name})
        trial = evaluate(data, without)
        if trial.gap_held_out * (1 - MIN_GAIN) <= fit.gap_held_out:
            kept = tuple(n for n in kept if n != name)
            fit = trial
    return kept, fit


def _bounds(screens: dict[str, Screening], names) -> dict:
    return {n: dict(screens[n].bounds) for n in names}


def _fixed(screens: dict[str, Screening], names) -> dict:
    return {n: tuple(screens[n].fixed) for n in names}


def _scan(screens: dict[str, Screening], names) -> dict:
    return {n: tuple(screens[n].scan) for n in names}


def search(data: DiagnosisData, base: FitResult) -> tuple[list[Step], SearchTrace]:
    """Add effects to ``base`` while they pay on held-out data; see the module docstring."""
    floor = noise_floor_percent(data)
    steps = [Step((), base, {})]
    current = base
    bounds_all: dict[str, dict] = {}
    fixed_all: dict[str, tuple] = {}
    trace = []
    for _ in range(MAX_ROUNDS):
        if current.gap_held_out <= FLOOR_FACTOR * floor:
            break
        cand = current.candidate
        ctx = screen_input(data, cand, current.v_sim)
        screens = screen_all(ctx, cand.names)
        quick = {n: quick_score(data, cand, n, s) for n, s in screens.items()}
        by_quick = sorted(quick, key=lambda n: quick[n].held_out_gap)[:TOP_BY_QUICK]
        by_score = sorted(screens, key=lambda n: -screens[n].score)[:TOP_BY_SCORE]
        pool = [n for n in by_quick if quick[n].held_out_gap < current.gap_held_out]
        pool += [n for n in by_score if screens[n].score >= MIN_SCORE and n not in pool]
        singles: dict[str, FitResult] = {}
        for n in pool:
            fits = [
                refit(
                    data,
                    start,
                    {**bounds_all, **_bounds(screens, [n])},
                    {**fixed_all, **_fixed(screens, [n])},
                    _scan(screens, [n]),
                    floor=floor,
                )
                for start in quick[n].starts
            ]
            singles[n] = min(fits, key=lambda f: f.gap_train)
        tried = [((n,), f.gap_held_out) for n, f in singles.items()]
        order = sorted(singles, key=lambda n: singles[n].gap_held_out)
        best_single = order[0] if order else None
        chosen: tuple[str, ...] = ()
        if (
            best_single
            and singles[best_single].gap_held_out <= (1 - MIN_GAIN) * current.gap_held_out
        ):
            chosen = (best_single,)
        best_fit = singles[best_single] if chosen else None
        # Pairs can pay where no single does only if some single at least helps.
        improving = (
            bool(order)
            and singles[order[0]].gap_held_out <= (1 - MIN_GAIN / 3) * current.gap_held_out
        )
        if improving and (not chosen or _explained(current, best_fit, floor) < PAIR_BELOW):
            for a, b in itertools.combinations(order[:PAIR_POOL], 2):
                if not compatible(b, [a]):
                    continue
                fa, fb = singles[a].candidate, singles[b].candidate
                start = Candidate(dict(fa.base), {**fa.effects, b: fb.effects[b]})
                pair = refit(
                    data,
                    start,
                    {**bounds_all, **_bounds(screens, [a, b])},
                    {**fixed_all, **_fixed(screens, [a, b])},
                    floor=floor,
                )
                tried.append(((a, b), pair.gap_held_out))
                reference = best_fit.gap_held_out if best_fit else current.gap_held_out
                if pair.gap_held_out <= (1 - MIN_GAIN) * reference:
                    chosen, best_fit = (a, b), pair
        trace.append(tuple(tried))
        if not chosen:
            break
        chosen, best_fit = _ablate(data, chosen, best_fit)
        if not chosen:
            # The refit only found a better optimum of the terms already there: keep it, name nothing.
            if best_fit.gap_held_out > (1 - MIN_GAIN) * current.gap_held_out:
                break
            steps[-1] = Step(steps[-1].added, best_fit, steps[-1].evidence)
            current = best_fit
            continue
        evidence = {
            n: f"{screens[n].evidence}; held-out gap {current.gap_held_out:.3g}% -> "
            f"{best_fit.gap_held_out:.3g}%"
            for n in chosen
        }
        bounds_all.update(_bounds(screens, chosen))
        fixed_all.update(_fixed(screens, chosen))
        steps.append(Step(chosen, best_fit, evidence))
        current = best_fit
    return steps, SearchTrace(tuple(trace), floor if math.isfinite(floor) else 0.0)
