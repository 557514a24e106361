"""Step 1: the base model, a linear block plus Coulomb friction per direction.

:func:`initial_base` is the one place that chooses where the starting values
come from: the project's identifier
(:func:`servobench.bench.identify.auto.identify_data`, on the same prepared
log) for open-loop logs, else -- or when the identifier gives up on the log --
an equation-error (inverse-dynamics) least-squares fit on the moving samples.
Either is only a start: :func:`fit_base` refits it on simulation error like
every candidate.

Viscous friction cannot be negative, but the best linear-plus-Coulomb fit of
an axis whose friction weakens with speed (a strong Stribeck curve) has a
negative, or vanishing, ``B``: that is the effect's signature, not a reason to
stop. The start then takes a small positive ``B`` and says why
(:attr:`BaseStart.note`); the search looks for the effect.

An axis that barely moves (a command under its breakaway, a velocity that
never leaves a step or two of its reading) gives a base fit that creeps where
the axis stands, and every effect that stops the creep would be named for
it. :func:`at_rest` holds such a base at rest instead, its Coulomb levels at
the largest command, when the base in motion does not pay against it and leaves
the held-out gap within the search's stop of the noise floor: the log then
shows nothing a model could add, and says so.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from servobench.bench.diagnose.data import DiagnosisData
from servobench.bench.diagnose.evidence import MIN_GAIN
from servobench.bench.diagnose.floor import sensor_floor_percent
from servobench.bench.diagnose.refit import FitResult, evaluate, refit
from servobench.bench.diagnose.screening import screen_input
from servobench.bench.diagnose.search import FLOOR_FACTOR
from servobench.bench.diagnose.simulate import Candidate
from servobench.bench.identify.auto import identify_data
from servobench.errors import IdentificationError
from servobench.sim_backend.physics.effects.spec import base_fit

#: Smallest starting ``B``, as a share of rms(command) / rms(velocity) on the moving samples:
#: below it the viscous term is lost in the friction and the fit is called velocity-weakening.
B_MIN_SHARE = 0.02


@dataclass(frozen=True)
class BaseStart:
    """Starting base model ``M, B, coulomb_pos, coulomb_neg``, where it came from, and a note
    when the best fit was not physical (empty otherwise)."""

    base: dict[str, float]
    source: str
    note: str = ""


def _scale(data: DiagnosisData) -> tuple[float, dict[str, float]]:
    """``rms(u) / rms(v)`` on the moving samples, and the unconstrained equation-error fit."""
    ctx = screen_input(
        data,
        Candidate({"M": 1.0, "B": 1.0, "coulomb_pos": 0.0, "coulomb_neg": 0.0}),
        [r.v for r in data.segments],
    )
    if int(ctx.moving.sum()) < 10:
        raise IdentificationError("too few samples in motion to identify the base model")
    coef, _ = base_fit(ctx)
    m = ctx.moving
    u, v = ctx.cat("u_f")[m], ctx.cat("v_f")[m]
    scale = float(np.sqrt(np.mean(u * u)) / max(np.sqrt(np.mean(v * v)), 1e-300))
    fit = dict(zip(("M", "B", "coulomb_pos", "coulomb_neg"), (float(c) for c in coef), strict=True))
    return scale, fit


def physical(fit: dict[str, float], scale: float, source: str) -> BaseStart:
    """A physical start from a fit: ``B`` at least :data:`B_MIN_SHARE` of ``scale``, Coulomb >= 0.

    Raises
    ------
    IdentificationError
        ``M`` is not positive (or the fit not finite): the log does not determine the inertia.
    """
    M, B = fit["M"], fit["B"]
    if not (np.isfinite(list(fit.values())).all() and M > 0):
        raise IdentificationError(
            f"the base fit is not physical (M = {M:.3g}, B = {B:.3g}): too little excitation? "
            "Excite with larger, faster-changing commands"
        )
    floor = B_MIN_SHARE * scale
    note = ""
    if floor > B:
        note = (
            f"the best linear-plus-Coulomb fit has B = {B:.3g} (M = {M:.3g}): viscous friction "
            f"cannot be {'negative' if B < 0 else 'that small'}; friction that weakens with speed "
            f"(a Stribeck curve) does this, so the base model starts from B = {floor:.3g} and the "
            "search looks for it"
        )
    base = {
        "M": M,
        "B": max(B, floor),
        "coulomb_pos": max(fit["coulomb_pos"], 0.0),
        "coulomb_neg": max(fit["coulomb_neg"], 0.0),
    }
    return BaseStart(base, source, note)


def initial_base(data: DiagnosisData) -> BaseStart:
    """Starting base model: the project's identifier on open-loop logs, else equation error."""
    scale, ee = _scale(data)
    equation_error = "equation error (inverse dynamics) on the moving samples"
    if data.horizon_s is not None:  # closed loop: the identifier assumes open-loop runs
        return physical(ee, scale, equation_error)
    try:
        result = identify_data(data.prepared)
    except ValueError:  # IdentificationError, or a plant the identifier could not simulate
        return physical(ee, scale, equation_error)
    model = result.model
    fit = {
        "M": float(model.M),
        "B": float(model.B),
        "coulomb_pos": float(model.coulomb_pos),
        "coulomb_neg": float(model.coulomb_neg),
    }
    if not fit["M"] > 0:
        return physical(ee, scale, equation_error)
    start = physical(fit, scale, f"servobench identify ({result.method})")
    if ee["B"] < B_MIN_SHARE * scale and (not start.note or ee["B"] < 0 <= fit["B"]):
        # The identifier may keep B positive by construction (or absorb part of the friction
        # curve in the drive's delay): the free fit tells, the more clearly where its B is negative.
        start = BaseStart(start.base, start.source, physical(ee, scale, equation_error).note)
    return start


def fit_base(data: DiagnosisData, start: BaseStart | None = None) -> FitResult:
    """The base model refitted on simulation error (training samples)."""
    start = initial_base(data) if start is None else start
    return refit(data, Candidate(start.base), bounds={})


def at_rest(data: DiagnosisData, fit: FitResult) -> tuple[FitResult, str] | None:
    """The base ``fit`` held at rest (both Coulomb levels at the largest command [command
    units]) with a note saying why, where ``fit`` does not pay against it on the training
    samples (:data:`~.evidence.MIN_GAIN` lower) and its held-out gap is within
    :data:`~.search.FLOOR_FACTOR` of the noise floor; else None.
    Its ``M`` and ``B`` are the fit's, undetermined by a log at rest (no sigma)."""
    top = max(float(np.max(np.abs(r.u))) for r in data.segments)
    held = evaluate(data, Candidate({**fit.candidate.base, "coulomb_pos": top, "coulomb_neg": top}))
    if fit.gap_train <= (1.0 - MIN_GAIN) * held.gap_train:  # motion the log shows: it pays
        return None
    floor = sensor_floor_percent(data, held.v_sim)
    if not held.gap_held_out <= FLOOR_FACTOR * floor:
        return None
    note = (
        f"the axis does not move beyond what the sensor's noise shows: a base model held at rest "
        f"(Coulomb levels at the largest command, {top:.3g}) leaves {held.gap_train:.3g}% on the "
        f"training samples, the best one in motion {fit.gap_train:.3g}%, and the "
        f"noise floor is {floor:.3g}%. M and B are not determined and no effect can be named: "
        "excite with a larger command, above the breakaway"
    )
    return held, note
