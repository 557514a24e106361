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

from servobench.bench.diagnose.data import DiagnosisData, noise_floor_percent
from servobench.bench.diagnose.refit import FitResult, evaluate, refit
from servobench.bench.diagnose.screening import (
    QuickScore,
    compatible,
    quick_score,
    screen_all,
    screen_input,
)
from servobench.bench.diagnose.simulate import Candidate
from servobench.sim_backend.physics.effects.spec import Screening

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


@dataclass
class _Fitter:
    """Refits candidates of one search with the bounds, grids and scans screening proposed."""

    data: DiagnosisData
    floor: float
    bounds: dict[str, dict]
    fixed: dict[str, tuple]
    screens: dict[str, Screening]

    def fit(self, start: Candidate, new: tuple[str, ...], scan: bool = True) -> FitResult:
        s = self.screens
        return refit(
            self.data,
            start,
            {**self.bounds, **{n: dict(s[n].bounds) for n in new}},
            {**self.fixed, **{n: tuple(s[n].fixed) for n in new}},
            {n: tuple(s[n].scan) for n in new} if scan else None,
            floor=self.floor,
        )

    def accept(self, names: tuple[str, ...]) -> None:
        """Later rounds keep refitting accepted terms within their screening's bounds."""
        self.bounds.update({n: dict(self.screens[n].bounds) for n in names})
        self.fixed.update({n: tuple(self.screens[n].fixed) for n in names})


def _pool(
    current: FitResult, screens: dict[str, Screening], quick: dict[str, QuickScore]
) -> list[str]:
    """Singles worth a refit: best quick guesses that beat the current model, best scores."""
    by_quick = sorted(quick, key=lambda n: quick[n].held_out_gap)[:TOP_BY_QUICK]
    by_score = sorted(screens, key=lambda n: -screens[n].score)[:TOP_BY_SCORE]
    pool = [n for n in by_quick if quick[n].held_out_gap < current.gap_held_out]
    return pool + [n for n in by_score if screens[n].score >= MIN_SCORE and n not in pool]


def _round(
    fitter: _Fitter, current: FitResult, quick: dict[str, QuickScore], trace: list
) -> tuple[tuple[str, ...], FitResult | None]:
    """One round of additions: the chosen names (possibly none) and their fit."""
    singles: dict[str, FitResult] = {}
    for n in _pool(current, fitter.screens, quick):
        fits = [fitter.fit(start, (n,)) for start in quick[n].starts]
        singles[n] = min(fits, key=lambda f: f.gap_train)
    tried = [((n,), f.gap_held_out) for n, f in singles.items()]
    trace.append(tried)
    order = sorted(singles, key=lambda n: singles[n].gap_held_out)
    if not order:
        return (), None
    chosen: tuple[str, ...] = ()
    best = None
    if singles[order[0]].gap_held_out <= (1 - MIN_GAIN) * current.gap_held_out:
        chosen, best = (order[0],), singles[order[0]]
    # Pairs can pay where no single does only if some single at least helps.
    improving = singles[order[0]].gap_held_out <= (1 - MIN_GAIN / 3) * current.gap_held_out
    if not improving or (
        best is not None and _explained(current, best, fitter.floor) >= PAIR_BELOW
    ):
        return chosen, best
    for a, b in itertools.combinations(order[:PAIR_POOL], 2):
        if not compatible(b, [a]):
            continue
        fa, fb = singles[a].candidate, singles[b].candidate
        pair = fitter.fit(Candidate(dict(fa.base), {**fa.effects, b: fb.effects[b]}), (a, b), False)
        tried.append(((a, b), pair.gap_held_out))
        reference = best.gap_held_out if best is not None else current.gap_held_out
        if pair.gap_held_out <= (1 - MIN_GAIN) * reference:
            chosen, best = (a, b), pair
    return chosen, best


def search(data: DiagnosisData, base: FitResult) -> tuple[list[Step], SearchTrace]:
    """Add effects to ``base`` while they pay on held-out data; see the module docstring."""
    floor = noise_floor_percent(data)
    steps = [Step((), base, {})]
    current = base
    fitter = _Fitter(data, floor, {}, {}, {})
    trace: list[list] = []
    for _ in range(MAX_ROUNDS):
        if current.gap_held_out <= FLOOR_FACTOR * floor:
            break
        cand = current.candidate
        fitter.screens = screen_all(screen_input(data, cand, current.v_sim), cand.names)
        quick = {n: quick_score(data, cand, n, s) for n, s in fitter.screens.items()}
        chosen, best = _round(fitter, current, quick, trace)
        if best is None or not chosen:
            break
        chosen, best = _ablate(data, chosen, best)
        if not chosen:
            # The refit only found a better optimum of the terms already there: keep it, name nothing.
            if best.gap_held_out > (1 - MIN_GAIN) * current.gap_held_out:
                break
            steps[-1] = Step(steps[-1].added, best, steps[-1].evidence)
            current = best
            continue
        evidence = {
            n: f"{fitter.screens[n].evidence}; held-out gap {current.gap_held_out:.3g}% -> "
            f"{best.gap_held_out:.3g}%"
            for n in chosen
        }
        fitter.accept(chosen)
        steps.append(Step(chosen, best, evidence))
        current = best
    rounds = tuple(tuple(r) for r in trace)
    return steps, SearchTrace(rounds, floor if math.isfinite(floor) else 0.0)
