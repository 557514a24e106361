"""``offset`` -- a constant force on the axis (gravity, amplifier or sensor offset).

Model: the command becomes ``u + offset`` [command units]. In motion this is
exactly a shift of the per-direction Coulomb levels (``coulomb_pos - offset``,
``coulomb_neg + offset``), so the base model absorbs any offset smaller than the
Coulomb level; the term is identifiable only when it exceeds one of them and
the axis drifts or accelerates without command (a negative Coulomb level).
"""

from __future__ import annotations

import numpy as np

from servobench.sim_backend.physics.effects.spec import (
    EffectSpec,
    ParamSpec,
    Screening,
    ScreenInput,
    Terms,
    base_columns,
    regress,
    target,
)

EFFECT = EffectSpec(
    name="offset",
    summary="constant force added to the command",
    params=(ParamSpec("offset", "offset", "command units", "force added to u", default=None),),
    signature="the free per-direction Coulomb fit needs a negative level: a force pushes one way "
    "whatever the motion (beyond that it is indistinguishable from Coulomb asymmetry)",
    fit="equation error with the Coulomb levels unconstrained; the offset is the shift that makes "
    "both levels non-negative and equal, then refit on simulation error",
)


def contribute(p, plant, terms: Terms) -> None:
    off = float(p["offset"])
    terms.inputs.append((40, lambda u: u + off))


def screen(ctx: ScreenInput) -> Screening:
    cols, y = base_columns(ctx), target(ctx)
    coef, sse_free = regress(cols, y)
    fcp, fcn = coef[2], coef[3]
    span = float(np.max(np.abs(ctx.cat("u")))) or 1.0
    bounds = {"offset": (-span, span)}
    guess = 0.5 * (fcn - fcp)
    if fcp >= 0 and fcn >= 0:
        return Screening(0.0, {"offset": guess}, bounds, "Coulomb levels are both positive")
    # Cost of forcing the negative level to zero: what only an offset can explain.
    keep = [c for i, c in enumerate(cols) if i != (2 if fcp < 0 else 3)]
    _, sse_con = regress(keep, y)
    score = max(0.0, 1.0 - sse_free / sse_con) if sse_con > 0 else 0.0
    side = "positive" if fcp < 0 else "negative"
    evidence = (
        f"the free Coulomb fit puts the {side}-direction level below zero: a constant force "
        f"acts whatever the motion (equation error {100 * score:.0f}% lower than with that level at zero)"
    )
    base = {"M": coef[0], "B": coef[1], "coulomb_pos": fcp + guess, "coulomb_neg": fcn - guess}
    return Screening(score, {"offset": guess}, bounds, evidence, base=base)
