"""Discrepancy workflow: find where the model and the data disagree, name the missing effect.

1. Identify the base model (linear block + Coulomb per direction), :mod:`.basefit`.
2. Simulate it on the log's command and compare with measured velocity, :mod:`.simulate`.
3. Locate the disagreement in time, against velocity, position, acceleration
   and direction, and in frequency, :mod:`.signatures`.
4. Rank the library's effects by their signatures and choose over
   combinations on held-out data, :mod:`.screening`, :mod:`.search`; a term is
   added only when it pays by a margin the noise cannot produce, :mod:`.evidence`.
5. Refit everything on simulation error (:mod:`.refit`) and repeat while it pays.
6. Judge the final model against the noise floor: ``explained`` or
   ``unexplained``, and where the residual lives, :mod:`.verdict`; say which
   parameters only the data fix together, :mod:`.families`.

``diagnose(log)`` returns a :class:`Diagnosis`; :mod:`servobench.bench.report.diagnose`
turns it into JSON, ``model.json``, a comparison CSV and a Markdown report with plots.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

from servobench.bench.blas_threads import on_one_blas_thread
from servobench.bench.diagnose.basefit import BaseStart, at_rest, fit_base, initial_base
from servobench.bench.diagnose.data import DiagnosisData, prepare
from servobench.bench.diagnose.families import Family, offset_family
from servobench.bench.diagnose.floor import sensor_floor_percent
from servobench.bench.diagnose.screening import COMPANIONS
from servobench.bench.diagnose.search import SearchTrace, Step, search
from servobench.bench.diagnose.signatures import Signatures, compute_signatures
from servobench.bench.diagnose.simulate import Candidate
from servobench.bench.diagnose.verdict import Verdict, judge
from servobench.bench.log.io import ExperimentLog
from servobench.sim_backend.physics import effects as library
from servobench.sim_backend.physics.effects import position_friction

__all__ = ["Diagnosis", "NamedEffect", "diagnose"]


@dataclass(frozen=True)
class NamedEffect:
    """An effect the diagnosis added: name, fitted parameters (those of the final model), the
    signature that named it, and its rivals: effects that fit the held-out data as well when
    it was named (the log cannot tell them apart; it is named for the lower held-out gap)."""

    name: str
    parameters: dict[str, float]
    evidence: str
    rivals: tuple[str, ...] = ()


@dataclass(frozen=True)
class Diagnosis:
    """Result of :func:`diagnose`.

    Attributes
    ----------
    effects : tuple of NamedEffect
        Effects added, in order, with the final model's parameters.
    gap_before, gap_after : float
        NRMSE [%] of simulated against measured velocity, base model and final model.
    steps : tuple of Step
        The base model and each accepted addition, with fits.
    signatures : Signatures
        Where the base model disagrees with the data.
    data : DiagnosisData
    trace : SearchTrace
    verdict : Verdict
        Whether the final model explains the data, the noise floor, where the residual lives.
    start : BaseStart
        Where the base model's starting values came from.
    families : tuple of Family
        Parameters the data fix only together.
    notes : tuple of str
        Caveats: an incomplete log, a derived velocity, an unphysical base fit.
    """

    effects: tuple[NamedEffect, ...]
    gap_before: float
    gap_after: float
    steps: tuple[Step, ...]
    signatures: Signatures
    data: DiagnosisData
    trace: SearchTrace
    verdict: Verdict
    start: BaseStart
    families: tuple[Family, ...] = ()
    notes: tuple[str, ...] = ()

    @property
    def final(self) -> Candidate:
        """The final model: base and effects as refitted together."""
        return self.steps[-1].fit.candidate

    @property
    def base(self) -> dict[str, float]:
        """Base parameters of the final model (refitted with its effects), the Coulomb levels
        net of a companion force (:data:`.screening.COMPANIONS`)."""
        return net_base(self.final, tuple(e.name for e in self.effects))

    @property
    def base_before(self) -> dict[str, float]:
        """Base parameters fitted before any effect was added."""
        return dict(self.steps[0].fit.candidate.base)


def companion_force(final: Candidate, named: tuple[str, ...]) -> float:
    """The constant force [command units] the final model carries as part of a named effect
    (not named itself), 0 when none."""
    for owner, c in COMPANIONS.items():
        if owner in named and c not in named and c in final.effects:
            return float(final.effects[c]["offset"])
    return 0.0


def net_base(final: Candidate, named: tuple[str, ...]) -> dict[str, float]:
    """The final base with the Coulomb levels net of a companion force: what the axis shows."""
    base = dict(final.base)
    o = companion_force(final, named)
    if o:
        base["coulomb_pos"] = float(base["coulomb_pos"]) - o
        base["coulomb_neg"] = float(base["coulomb_neg"]) + o
    return base


def rival_note(e: NamedEffect) -> str:
    """The note that says an effect was named among others the log cannot tell apart."""
    others = " and ".join(e.rivals) if len(e.rivals) < 3 else ", ".join(e.rivals)
    verb = "fits" if len(e.rivals) == 1 else "fit"
    return (
        f"{e.name} is named for the lowest held-out gap, but {others} {verb} the held-out data "
        "as well, within what the noise allows: this log cannot tell them apart. Excite so that "
        "they differ (a command with more levels and amplitudes than a two-level pair, or the "
        "axis over more of its travel) and diagnose that log"
    )


def named_parameters(
    name: str, values: dict[str, float], base: dict[str, float], force: float = 0.0
) -> dict:
    """An effect's parameters as reported: unused spline knots left out, the directional
    viscous coefficients spelled out, a Stribeck curve's static level in each direction
    (``fs_pos``, ``fs_neg``, net of the companion ``force``; ``fs`` their mean)."""
    params = dict(values)
    if name == "stribeck":
        params["fs_pos"] = params["fs"] - force
        params["fs_neg"] = params["fs"] + force
    if name == "viscous_asymmetry":
        params["B_pos"] = base["B"] + params["dB"]
        params["B_neg"] = base["B"] - params["dB"]
    if name == "position_friction":
        params = position_friction.compact(params)
    return params


@on_one_blas_thread  # see bench.blas_threads: thousands of small, tall solves
def diagnose(
    log: ExperimentLog,
    horizon_s: float | None = None,
    *,
    effects: Iterable[str] | None = None,
    progress: Callable[[str], None] | None = None,
) -> Diagnosis:
    """Run the discrepancy workflow on a log.

    Parameters
    ----------
    log : ExperimentLog
        Runs with ``u`` and ``v`` and/or ``x``.
    horizon_s : float, optional
        Compare by predictions restarted every ``horizon_s`` [s] instead of whole-run
        simulation (default for logs whose ``loop`` metadata says closed).
    effects : iterable of str, optional
        Library effects the search may name (default: all of them).
    progress : callable, optional
        Called with a short message as each stage starts.

    Raises
    ------
    IdentificationError
        The log cannot yield a base model.
    UsageError
        Unknown effect names, a non-positive horizon.
    """
    return _diagnose(log, horizon_s, effects, progress)


def _diagnose(
    log: ExperimentLog,
    horizon_s: float | None,
    effects: Iterable[str] | None,
    progress: Callable[[str], None] | None,
) -> Diagnosis:
    say = progress or (lambda _m: None)
    allowed = None if effects is None else tuple(library.module(n).EFFECT.name for n in effects)
    data = prepare(log, horizon_s)
    say("fitting the base model")
    start = initial_base(data)
    base = fit_base(data, start)
    rest = at_rest(data, base)
    if rest is not None:
        base, rest_note = rest
    signatures = compute_signatures(data, base.v_sim)
    steps, trace = search(data, base, sensor_floor_percent(data, base.v_sim), allowed, say)
    say("judging the final model against the noise floor")
    last = steps[-1].fit
    verdict = judge(data, last.candidate, last.v_sim, last.gap)
    final = last.candidate
    names = tuple(n for step in steps[1:] for n in step.added)
    force = companion_force(final, names)
    base_net = net_base(final, names)
    named = []
    for step in steps[1:]:
        for name in step.added:
            params = named_parameters(name, dict(final.effects[name]), dict(final.base), force)
            clause = signatures.support(name)
            evidence = step.evidence[name] if not clause else f"{step.evidence[name]}; {clause}"
            rivals = step.rivals.get(name, ())
            named.append(NamedEffect(name, params, evidence, rivals))
    shown = {k: v for k, v in final.effects.items() if k in names}
    family = offset_family(base_net, shown, data.units.of("u"))
    notes = tuple(data.notes) + ((start.note,) if start.note else ())
    notes += (rest_note,) if rest is not None else ()
    notes += tuple(rival_note(e) for e in named if e.rivals)
    return Diagnosis(
        tuple(named),
        steps[0].fit.gap,
        last.gap,
        tuple(steps),
        signatures,
        data,
        trace,
        verdict,
        start,
        (family,) if family else (),
        notes,
    )
