"""Discrepancy workflow: find where the model and the data disagree, name the missing effect.

1. Identify the base model (linear block + Coulomb per direction), :mod:`.basefit`.
2. Simulate it on the log's command and compare with measured velocity, :mod:`.simulate`.
3. Locate the disagreement in time, against velocity, position, acceleration
   and direction, and in frequency, :mod:`.signatures`.
4. Rank the library's effects by their signatures and choose over
   combinations on held-out data, :mod:`.screening`, :mod:`.search`.
5. Refit everything on simulation error (:mod:`.refit`) and repeat while it pays.

``diagnose(log)`` returns a :class:`Diagnosis`; :mod:`.report` turns it
into JSON, a comparison CSV and a Markdown report with plots.
"""

from __future__ import annotations

from dataclasses import dataclass

from servobench.bench.diagnose.basefit import fit_base
from servobench.bench.diagnose.data import DiagnosisData, prepare
from servobench.bench.diagnose.search import SearchTrace, Step, search
from servobench.bench.diagnose.signatures import Signatures, compute_signatures
from servobench.bench.logio import ExperimentLog

__all__ = ["Diagnosis", "NamedEffect", "diagnose"]


@dataclass(frozen=True)
class NamedEffect:
    """An effect the diagnosis added: name, fitted parameters, the signature that named it."""

    name: str
    parameters: dict[str, float]
    evidence: str


@dataclass(frozen=True)
class Diagnosis:
    """Result of :func:`diagnose`.

    Attributes
    ----------
    effects : tuple of NamedEffect
        Effects added, in order.
    gap_before, gap_after : float
        NRMSE [%] of simulated against measured velocity, base model and final model.
    steps : tuple of Step
        The base model and each accepted addition, with fits.
    signatures : Signatures
        Where the base model disagrees with the data.
    data : DiagnosisData
    trace : SearchTrace
    """

    effects: tuple[NamedEffect, ...]
    gap_before: float
    gap_after: float
    steps: tuple[Step, ...]
    signatures: Signatures
    data: DiagnosisData
    trace: SearchTrace

    @property
    def base(self) -> dict[str, float]:
        return dict(self.steps[-1].fit.candidate.base)


def diagnose(log: ExperimentLog, horizon_s: float | None = None) -> Diagnosis:
    """Run the discrepancy workflow on a log.

    Parameters
    ----------
    log : ExperimentLog
        Runs with ``u`` and ``v`` and/or ``x``.
    horizon_s : float, optional
        Compare by predictions restarted every ``horizon_s`` [s] instead of whole-run
        simulation (default for logs whose ``loop`` metadata says closed).

    Raises
    ------
    IdentificationError
        The log cannot yield a base model.
    """
    data = prepare(log, horizon_s)
    base = fit_base(data)
    signatures = compute_signatures(data, base.v_sim)
    steps, trace = search(data, base)
    final = steps[-1].fit.candidate
    named = []
    for step in steps[1:]:
        for name in step.added:
            params = dict(final.effects[name])
            if name == "viscous_asymmetry":
                params["B_pos"] = final.base["B"] + params["dB"]
                params["B_neg"] = final.base["B"] - params["dB"]
            clause = signatures.support(name)
            evidence = step.evidence[name] if not clause else f"{step.evidence[name]}; {clause}"
            named.append(NamedEffect(name, params, evidence))
    return Diagnosis(
        tuple(named),
        steps[0].fit.gap,
        steps[-1].fit.gap,
        tuple(steps),
        signatures,
        data,
        trace,
    )
