"""Steps 4-5: rank candidate effects, refit combinations, keep what pays on held-out data.

Each round screens every library effect against the current model's residual
(signature score and a quick simulation of the guess), refits the most
promising single additions and the pairs among them, and compares them on
held-out samples. A candidate *pays* when its held-out gap is :data:`MIN_GAIN`
below the reference's and the gain is one the noise cannot produce
(:data:`MIN_Z` standard deviations of what noise adds to it, :mod:`.evidence`). Pairs compete with
singles so that two wrong terms that together mimic one missing effect
(viscous plus drag for a Stribeck curve) do not win by greed: a pair is taken
only when it pays against the best single, a single when it pays against the
current model. A term that joins a model already holding effects (or comes
in a pair) must also pay against the model without it refitted from the joint
fit's values: otherwise a first effect stuck in a poor optimum lets a second
soak up its residual. After each round that adds a term, each term of the
earlier rounds must still pay against the model refitted without it
(backward elimination, :func:`_eliminate`): a delay named for the residual of a
resonant load is dropped once the resonance is in; when the search ends, every
term of a model holding several must (a Stribeck curve that made up for a play
stuck in a poor optimum goes once the play is refitted). Models refitted
without a term rescan their other terms' rugged parameters. An effect with a companion
(:data:`.screening.COMPANIONS`: a Stribeck curve with its static level per
direction) is refitted, kept and dropped with it. Every candidate refitted
carries the reason it was chosen or rejected (:class:`Tried`). Where nothing of a
round's pool pays and the model is still far above the noise floor
(:data:`WIDEN_ABOVE`), every other effect whose quick guess beats it is refitted
too: a base model far off (a closed loop hunting in a play) can hide the
missing effect's signature. The loop stops when nothing pays, or when the
model reaches the sensor-noise floor.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

from servobench.bench.diagnose.data import DiagnosisData
from servobench.bench.diagnose.evidence import MIN_GAIN, MIN_Z, Payoff, payoff
from servobench.bench.diagnose.refit import FitResult, evaluate, refit, with_covariance
from servobench.bench.diagnose.screening import (
    COMPANIONS,
    QuickScore,
    companion_bounds,
    compatible,
    quick_score,
    screen_all,
    screen_input,
    without,
)
from servobench.bench.diagnose.simulate import Candidate
from servobench.bench.diagnose.verdict import EXACT_GAP_PERCENT
from servobench.sim_backend.physics import effects as library
from servobench.sim_backend.physics.effects.spec import Screening

#: Singles refitted per round: the best quick guesses that beat the current model, and
#: the best screening scores of at least MIN_SCORE.
TOP_BY_QUICK = 2
TOP_BY_SCORE = 3
MIN_SCORE = 0.05
#: Singles whose pairs are refitted.
PAIR_POOL = 3
#: Rounds of additions.
MAX_ROUNDS = 3
#: A gap within this factor of the sensor-noise floor leaves nothing to explain.
FLOOR_FACTOR = 1.25
#: Pairs are tried only when the best single leaves more than this share of the
#: unexplained (above-noise) residual energy.
PAIR_BELOW = 0.8
#: When nothing in the pool pays and the held-out gap is above this multiple of the noise
#: floor, every other effect whose quick guess beats the current model is refitted too: far
#: from the floor a screening read off a poor base model can rank the missing effect low.
#: Against the base model alone, every other effect: a base fitted without a large play is
#: far off (M 1.5-2.5 times small), and the play's guess on it simulates worse than the base
#: until its refit moves the base too. Its residual is then no more predictable from the log's
#: signals than coloured noise is (12 % of it on a single run), so that cannot tell the two
#: apart: coloured noise under a control costs 0.6 -> 0.9 s a diagnosis. A model that already
#: reproduces the log within :data:`~.verdict.EXACT_GAP_PERCENT` (noise-free data) is not far.
WIDEN_ABOVE = 2.0

Progress = Callable[[str], None]


@dataclass(frozen=True)
class Step:
    """One accepted addition (or the base model, with ``added == ()``); ``rivals`` names, per
    effect added alone, the other effects that fit the held-out data as well (:func:`_decide`)."""

    added: tuple[str, ...]
    fit: FitResult
    evidence: dict[str, str]
    rivals: dict[str, tuple[str, ...]] = field(default_factory=dict)


@dataclass(frozen=True)
class Tried:
    """A refitted candidate of one round: its held-out gap [%], whether it was chosen, and why."""

    effects: tuple[str, ...]
    gap_held_out: float
    chosen: bool
    reason: str


@dataclass(frozen=True)
class Round:
    """One round: the current model's held-out gap [%], the candidates refitted, the
    effects screened but not refitted ``(name, screening score, quick held-out gap [%])``, and
    the effects that fit as well as the single one chosen (:func:`_decide`)."""

    reference_gap: float
    tried: tuple[Tried, ...]
    not_refitted: tuple[tuple[str, float, float], ...]
    rivals: tuple[str, ...] = ()


@dataclass(frozen=True)
class SearchTrace:
    """What each round tried, the sensor-noise floor [%] the stop rule used, why it stopped."""

    rounds: tuple[Round, ...]
    noise_floor: float
    stop: str


def _explained(before: FitResult, after: FitResult, floor: float) -> float:
    """Share of the above-noise held-out residual energy that ``after`` removes."""
    room = before.gap_held_out**2 - floor**2
    if room <= 0:
        return 1.0
    return (before.gap_held_out**2 - after.gap_held_out**2) / room


def _ablate(
    data: DiagnosisData, chosen: tuple[str, ...], fit: FitResult, present: tuple[str, ...] = ()
) -> tuple[tuple[str, ...], FitResult, list[str]]:
    """Drop new terms the fitted model does not need (it does as well on held-out data without);
    a term goes with its companion unless that was ``present`` before it."""
    kept, dropped = chosen, []
    for name in chosen:
        cand = fit.candidate
        rest = without(dict(cand.effects), name, present + kept)
        trial = evaluate(data, Candidate(dict(cand.base), rest))
        if trial.gap_held_out * (1 - MIN_GAIN) <= fit.gap_held_out:
            kept = tuple(n for n in kept if n != name)
            dropped.append(name)
            fit = with_covariance(data, trial, fit)  # evaluated only: its sigma from a Jacobian there
    return kept, fit, dropped


@dataclass
class _Fitter:
    """Refits candidates of one search with the bounds, grids and scans screening proposed."""

    data: DiagnosisData
    floor: float
    bounds: dict[str, dict]
    fixed: dict[str, tuple]
    screens: dict[str, Screening]
    scans: dict[str, tuple] = field(default_factory=dict)

    def fit(
        self, start: Candidate, new: tuple[str, ...], scan: bool = True, rescan: bool = False
    ) -> FitResult:
        """Refit ``start`` with its ``new`` terms in their screening's bounds; ``scan``: scan
        the new terms' rugged parameters; ``rescan``: those of the accepted terms too (a model
        refitted without a term, whose rugged neighbours may have to move far)."""
        s = self.screens
        extra = {k: v for n in new for k, v in companion_bounds(n, start).items()}
        scans = {n: tuple(s[n].scan) for n in new} if scan else {}
        if rescan:
            scans.update({n: self.scans[n] for n in start.effects if self.scans.get(n)})
        return refit(
            self.data,
            start,
            {**extra, **self.bounds, **{n: dict(s[n].bounds) for n in new}},
            {**self.fixed, **{n: tuple(s[n].fixed) for n in new}},
            {n: v for n, v in scans.items() if v} or None,
            floor=self.floor,
        )

    def accept(self, names: tuple[str, ...], cand: Candidate) -> None:
        """Later rounds keep refitting accepted terms (and their companions, as in ``cand``)
        within their screening's bounds."""
        for n in names:
            for k, v in companion_bounds(n, cand).items():
                self.bounds.setdefault(k, v)
        self.bounds.update({n: dict(self.screens[n].bounds) for n in names})
        self.fixed.update({n: tuple(self.screens[n].fixed) for n in names})
        self.scans.update({n: tuple(self.screens[n].scan) for n in names})


def _refit_ablate(
    fitter: _Fitter, current: FitResult, chosen: tuple[str, ...], fit: FitResult
) -> tuple[tuple[str, ...], FitResult, list[str]]:
    """Drop new terms that pay only against a poorer fit of the others.

    When the model already holds effects, or a pair comes in together, each new term must
    pay against the model without it *refitted* from the joint fit's values: a first effect
    fitted into a poor optimum (a Stribeck curve whose velocity got stuck) leaves a residual
    a second effect soaks up, and the joint fit of the two moves the first one's parameters
    to where it explains that residual alone.
    """
    if not (current.candidate.effects or len(chosen) > 1):
        return chosen, fit, []
    kept, dropped = list(chosen), []
    for name in chosen:
        cand = fit.candidate
        rest = without(dict(cand.effects), name, (*current.candidate.effects, *kept))
        others = tuple(n for n in kept if n != name)
        trial = fitter.fit(Candidate(dict(cand.base), rest), others, rescan=True)
        if not payoff(fitter.data, trial, fit).pays:
            kept.remove(name)
            dropped.append(name)
            fit = trial
    return tuple(kept), fit, dropped


def _companions_pay(
    fitter: _Fitter, current: FitResult, chosen: tuple[str, ...], fit: FitResult
) -> tuple[tuple[str, ...], FitResult, list[str]]:
    """A new term fitted with a companion (:data:`.screening.COMPANIONS`) must pay without
    it, refitted from the joint fit's values with the companion folded into the base (a
    Stribeck curve with one static level and the Coulomb levels net of the force); the
    companion stays only where it pays against that. Otherwise the companion's freedom
    lets the term stand in for what it is not (drag growing with the square of the speed)."""
    dropped: list[str] = []
    for name in chosen:
        c = COMPANIONS.get(name)
        cand = fit.candidate
        if c is None or c not in cand.effects or c in current.candidate.effects or c in chosen:
            continue
        o = float(cand.effects[c]["offset"])
        base = {**cand.base}
        base["coulomb_pos"] = max(float(base["coulomb_pos"]) - o, 0.0)
        base["coulomb_neg"] = max(float(base["coulomb_neg"]) + o, 0.0)
        rest = {k: dict(v) for k, v in cand.effects.items() if k != c}
        rest[name] = library.project(name, rest[name], base)
        plain = fitter.fit(Candidate(base, rest), chosen, scan=False)
        if not payoff(fitter.data, current, plain).pays:
            dropped.append(name)
            continue
        if not payoff(fitter.data, plain, fit).pays:
            fit = plain
    if dropped:
        return (), current, dropped
    return chosen, fit, []


#: Why a term with a companion was dropped (see :func:`_companions_pay`).
DROPPED_PLAIN = "without its companion it does not pay against the current model"


def _eliminate(fitter: _Fitter, steps: list[Step], final: bool = False) -> list[Step]:
    """Backward elimination: drop a term of an earlier round (of every round, ``final``) that
    the model with the new terms, refitted without it, no longer needs (it does as well on
    held-out data). A first effect named for a residual a later one explains better (a delay
    standing in for a resonant load) would otherwise stay named; and a term a later round's
    refit of its neighbours made redundant (a Stribeck curve that made up for a play stuck in
    a poor optimum) is dropped once the search ends."""
    fit = steps[-1].fit
    for step in steps[1:] if final else steps[1:-1]:
        for name in step.added:
            cand = fit.candidate
            others = tuple(n for st in steps[1:] for n in st.added if n != name)
            rest = without(dict(cand.effects), name, others)
            trial = fitter.fit(Candidate(dict(cand.base), rest), (), rescan=True)
            if payoff(fitter.data, trial, fit).pays:
                continue
            fit = trial
            steps = [
                Step(
                    tuple(n for n in st.added if n != name),
                    st.fit,
                    st.evidence,
                    {k: v for k, v in st.rivals.items() if k != name},
                )
                for st in steps
            ]
            steps = [st for i, st in enumerate(steps) if i == 0 or st.added]
            steps[-1] = replace(steps[-1], fit=fit)
    return steps


def _pool(
    current: FitResult, screens: dict[str, Screening], quick: dict[str, QuickScore]
) -> list[str]:
    """Singles worth a refit: best quick guesses that beat the current model, best scores, and
    every rugged effect (its screening asks for a scan) that scores and beats the current model.

    A rugged effect's quick guess cannot rank it: where cogging wells trap the axis, the run
    turns on where they lie, and a guess a few hundredths of a radian off the basin simulates
    no better than a wrong effect's (a single run trapped in wells of 2.9 times the Coulomb
    level: its guess, 44 % held out, was neither among the best two guesses nor the best three
    scores, and a saturation was named at 41 %; refitted, cogging reaches 1.7 %)."""
    by_quick = sorted(quick, key=lambda n: quick[n].held_out_gap)[:TOP_BY_QUICK]
    ranked = sorted(screens, key=lambda n: -screens[n].score)
    pool = [n for n in by_quick if quick[n].held_out_gap < current.gap_held_out]
    pool += [n for n in ranked[:TOP_BY_SCORE] if screens[n].score >= MIN_SCORE and n not in pool]
    pool += [n for n in ranked if screens[n].scan and screens[n].score >= MIN_SCORE and n not in pool
             and n in quick and quick[n].held_out_gap < current.gap_held_out]  # fmt: skip
    return pool


def _why_not(p: Payoff, against: str) -> str:
    """Why a candidate does not pay against ``against`` (its reference)."""
    if p.gain <= 0:
        return f"no better than {against} ({p.reference_gap:.3g}%) on held-out data"
    if p.gain < MIN_GAIN:
        return (
            f"only {100 * p.gain:.0f}% below {against} ({p.reference_gap:.3g}%) on held-out "
            f"data; a term must bring {100 * MIN_GAIN:.0f}%"
        )
    return (
        f"its held-out gain over {against} is within what the noise produces "
        f"(its drop of the squared error is {p.z:.1f} noise standard deviations, "
        f"{MIN_Z:g} needed)"
    )


def _decide(
    data: DiagnosisData, current: FitResult, singles: dict[str, FitResult], pairs: dict
) -> tuple[tuple[str, ...], FitResult | None, dict[tuple[str, ...], str], tuple[str, ...]]:
    """The round's choice, its fit, the reason for every candidate's outcome, and the chosen
    single's rivals: the other singles that pay against the current model and that it does
    not pay against, best first -- effects the log cannot tell apart from the one named (a
    saturation, a dead zone and a quantization of a two-level command all only move its
    two levels)."""
    reasons: dict[tuple[str, ...], str] = {}
    pays = {n: payoff(data, current, f) for n, f in singles.items()}
    eligible = sorted((n for n in singles if pays[n].pays), key=lambda n: singles[n].gap_held_out)
    for n in singles:
        if not pays[n].pays:
            reasons[(n,)] = _why_not(pays[n], "the current model")
    best = eligible[0] if eligible else None
    chosen, fit = ((best,), singles[best]) if best else ((), None)
    reference = singles[best] if best else current
    against = f"{best} alone" if best else "the current model"
    for key in sorted(pairs, key=lambda k: pairs[k].gap_held_out):
        p = payoff(data, reference, pairs[key])
        if p.pays and len(chosen) < 2:  # the best pair that pays
            chosen, fit = key, pairs[key]
        elif p.pays:
            reasons[key] = f"pays, but {'+'.join(chosen)} does better"
        else:
            reasons[key] = _why_not(p, against)
    for n in eligible:
        if (n,) != chosen:
            reasons[(n,)] = f"pays, but {'+'.join(chosen)} does better ({fit.gap_held_out:.3g}%)"
    if chosen:
        reasons[chosen] = (
            f"held-out gap {current.gap_held_out:.3g}% -> {fit.gap_held_out:.3g}%, the best "
            "candidate that pays"
        )
    rivals = ()
    if len(chosen) == 1:
        rivals = tuple(n for n in eligible[1:] if not payoff(data, singles[n], fit).pays)
    return chosen, fit, reasons, rivals


def _best_start(data: DiagnosisData, name: str, fits: list[FitResult]) -> FitResult:
    """The refit of effect ``name`` to keep, of those from its different starts: of one model
    order, the lowest training gap; of several (a spline's knot count, the module's ``order``),
    the lowest order, and a higher one only when it pays against it on held-out data."""
    def rank(f: FitResult) -> int:
        return library.order(name, f.candidate.effects[name])

    by_order: dict[int, FitResult] = {}
    for f in fits:
        k = rank(f)
        if k not in by_order or f.gap_train < by_order[k].gap_train:
            by_order[k] = f
    chosen = by_order[min(by_order)]
    for k in sorted(by_order)[1:]:
        if payoff(data, chosen, by_order[k]).pays:
            chosen = by_order[k]
    return chosen


def _round(
    fitter: _Fitter, current: FitResult, quick: dict[str, QuickScore], progress: Progress
) -> tuple[tuple[str, ...], FitResult | None, Round]:
    """One round of additions: the chosen names (possibly none), their fit and the round."""
    singles: dict[str, FitResult] = {}
    pool = _pool(current, fitter.screens, quick)
    for i, n in enumerate(pool, 1):
        progress(f"refitting {n} ({i}/{len(pool)})")
        fits = [fitter.fit(start, (n,)) for start in quick[n].starts]
        singles[n] = _best_start(fitter.data, n, fits)
    order = sorted(singles, key=lambda n: singles[n].gap_held_out)
    pairs: dict[tuple[str, str], FitResult] = {}
    top = singles[order[0]] if order else None
    # Pairs can pay where no single does only if some single at least helps.
    improving = top is not None and top.gap_held_out <= (1 - MIN_GAIN / 3) * current.gap_held_out
    if improving and _explained(current, top, fitter.floor) < PAIR_BELOW:
        for a, b in itertools.combinations(order[:PAIR_POOL], 2):
            if not compatible(b, [a]):
                continue
            progress(f"refitting the pair {a} + {b}")
            fa, fb = singles[a].candidate, singles[b].candidate
            start = Candidate(dict(fa.base), {**fb.effects, **fa.effects})
            pairs[(a, b)] = fitter.fit(start, (a, b), False)
    chosen, best, reasons, rivals = _decide(fitter.data, current, singles, pairs)
    reach = max(WIDEN_ABOVE * fitter.floor, EXACT_GAP_PERCENT)
    far = fitter.floor > 0 and current.gap_held_out > reach
    if not chosen and far:  # (a floor of 0: no sensor noise known, no scale for "far")
        every = not current.candidate.effects
        wider = [
            n
            for n in sorted(quick, key=lambda n: quick[n].held_out_gap)
            if n not in singles and (every or quick[n].held_out_gap < current.gap_held_out)
        ]
        for i, n in enumerate(wider, 1):
            progress(f"refitting {n} (nothing paid so far; {i}/{len(wider)})")
            fits = [fitter.fit(start, (n,)) for start in quick[n].starts]
            singles[n] = _best_start(fitter.data, n, fits)
        if wider:
            chosen, best, reasons, rivals = _decide(fitter.data, current, singles, pairs)
    tried = [
        Tried((n,), f.gap_held_out, (n,) == chosen, reasons.get((n,), ""))
        for n, f in singles.items()
    ] + [Tried(k, f.gap_held_out, k == chosen, reasons.get(k, "")) for k, f in pairs.items()]
    skipped = tuple(
        (n, float(fitter.screens[n].score), float(quick[n].held_out_gap))
        for n in fitter.screens
        if n not in singles
    )
    return chosen, best, Round(current.gap_held_out, tuple(tried), skipped, rivals)


#: Why ablation dropped terms (see :func:`_ablate` and :func:`_refit_ablate`).
DROPPED = "the refitted model does as well without"
DROPPED_REFIT = (
    "the model without, refitted from the joint fit, does as well (the term only made up for "
    "a poorer fit of the others)"
)


def _with_ablation(
    rnd: Round, chosen: tuple[str, ...], dropped: list[str], fit: FitResult, why: str
) -> Round:
    """The round with the chosen candidate's reason saying which terms ablation dropped."""
    if not dropped:
        return rnd
    tried = tuple(
        Tried(
            t.effects,
            t.gap_held_out,
            t.chosen,
            f"{t.reason}; then {', '.join(dropped)} dropped: {why} (held-out gap "
            f"{fit.gap_held_out:.3g}%)"
            if t.chosen
            else t.reason,
        )
        for t in rnd.tried
    )
    return Round(rnd.reference_gap, tried, rnd.not_refitted, rnd.rivals)


def search(
    data: DiagnosisData,
    base: FitResult,
    floor: float,
    effects: tuple[str, ...] | None = None,
    progress: Progress | None = None,
) -> tuple[list[Step], SearchTrace]:
    """Add effects to ``base`` while they pay on held-out data; see the module docstring.

    Parameters
    ----------
    floor : float
        Sensor-noise floor of the gap [%]: a model within :data:`FLOOR_FACTOR` of it stops
        the search.
    effects : tuple of str, optional
        The library effects to consider (default: all).
    progress : callable, optional
        Called with a short message as each stage starts.
    """
    say = progress or (lambda _m: None)
    steps = [Step((), base, {})]
    current = base
    fitter = _Fitter(data, floor, {}, {}, {})
    rounds: list[Round] = []
    stop = f"stopped after {MAX_ROUNDS} rounds"
    for number in range(1, MAX_ROUNDS + 1):
        if current.gap_held_out <= FLOOR_FACTOR * floor:
            stop = (
                f"the held-out gap {current.gap_held_out:.3g}% is within {FLOOR_FACTOR:g} times "
                f"the sensor-noise floor ({floor:.3g}%)"
            )
            break
        say(f"round {number}: screening the effect library")
        cand = current.candidate
        ctx = screen_input(data, cand, current.v_sim)
        fitter.screens = screen_all(ctx, cand.names, effects)
        quick = {n: quick_score(data, cand, n, s) for n, s in fitter.screens.items()}
        chosen, best, rnd = _round(
            fitter, current, quick, lambda m, k=number: say(f"round {k}: {m}")
        )
        if best is None or not chosen:
            rounds.append(rnd)
            stop = "nothing in the library pays on held-out data"
            break
        chosen, best, dropped = _ablate(data, chosen, best, tuple(current.candidate.effects))
        rnd = _with_ablation(rnd, chosen, dropped, best, DROPPED)
        chosen, best, dropped = _refit_ablate(fitter, current, chosen, best)
        rnd = _with_ablation(rnd, chosen, dropped, best, DROPPED_REFIT)
        chosen, best, dropped = _companions_pay(fitter, current, chosen, best)
        rounds.append(_with_ablation(rnd, chosen, dropped, best, DROPPED_PLAIN))
        if not chosen:
            # The refit only found a better optimum of the terms already there: keep it, name
            # nothing, and look again from there while it gains.
            if best.gap_held_out < current.gap_held_out:
                steps[-1] = replace(steps[-1], fit=best)
                gained = best.gap_held_out <= (1 - MIN_GAIN) * current.gap_held_out
                current = best
                if gained:
                    continue
            stop = "nothing in the library pays on held-out data"
            break
        evidence = {
            n: f"{fitter.screens[n].evidence}; held-out gap {current.gap_held_out:.3g}% -> "
            f"{best.gap_held_out:.3g}%"
            for n in chosen
        }
        fitter.accept(chosen, best.candidate)
        rivals = {chosen[0]: rnd.rivals} if len(chosen) == 1 and rnd.rivals else {}
        steps.append(Step(chosen, best, evidence, rivals))
        steps = _eliminate(fitter, steps)
        current = steps[-1].fit
    if sum(len(st.added) for st in steps) > 1:  # a lone term already paid against the base
        steps = _eliminate(fitter, steps, final=True)
    return steps, SearchTrace(tuple(rounds), floor if math.isfinite(floor) else 0.0, stop)
