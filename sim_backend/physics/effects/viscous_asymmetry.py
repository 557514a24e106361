"""``viscous_asymmetry`` -- viscous friction that differs with the direction of motion.

Model: ``B_pos = B + dB`` for ``v > 0`` and ``B_neg = B - dB`` for ``v < 0``
[command units * s / position unit], ``|dB| < B``. Piecewise linear: exact
under zero-order hold. (The EMPS axis: Fv+ = 166.7, Fv- = 240.4 N s/m.)
"""

from __future__ import annotations

from servobench.errors import UsageError
from servobench.sim_backend.physics.effects.spec import (
    EffectSpec,
    ParamSpec,
    Screening,
    ScreenInput,
    Terms,
    base_fit,
    explained,
    regress,
    target,
)

EFFECT = EffectSpec(
    name="viscous_asymmetry",
    summary="direction-dependent viscous friction",
    params=(
        ParamSpec(
            "dB",
            "visc_asym",
            "command units*s/unit",
            "half the difference B_pos - B_neg (B_pos = B + dB, B_neg = B - dB)",
            default=None,
        ),
    ),
    signature="the residual grows linearly with speed with a different slope in each direction; "
    "the force-velocity line has a kink at zero beyond the Coulomb step",
    fit="equation error with separate v+ and v- regressors, then simulation error",
)


def check(p, plant) -> None:
    if not abs(p["dB"]) < plant.B:
        raise UsageError(
            f"viscous_asymmetry: |visc_asym| = {abs(p['dB']):g} must be below B = {plant.B:g}"
        )


def contribute(p, plant, terms: Terms) -> None:
    terms.dB += float(p["dB"])


def screen(ctx: ScreenInput) -> Screening:
    m = ctx.moving
    a, v = ctx.cat("a_f")[m], ctx.cat("v_f")[m]
    y = target(ctx)
    _, sse0 = base_fit(ctx)
    cols = [a, v * (v > 0), v * (v < 0), (v > 0).astype(float), -(v < 0).astype(float)]
    coef, sse = regress(cols, y)
    Bp, Bn = coef[1], coef[2]
    B = 0.5 * (Bp + Bn)
    dB = 0.5 * (Bp - Bn)
    lim = 0.95 * abs(B) if B > 0 else 1.0
    score = explained(sse0, sse, 1, y.size)
    evidence = (
        f"the force-velocity slope differs by direction "
        f"(equation error {100 * (1 - sse / sse0):.0f}% lower than with one slope)"
        if sse0 > 0
        else "no equation error to explain"
    )
    base = {"M": coef[0], "B": B, "coulomb_pos": coef[3], "coulomb_neg": coef[4]}
    dB = max(-0.9 * lim, min(0.9 * lim, dB))
    return Screening(score, {"dB": dB}, {"dB": (-lim, lim)}, evidence, base=base)


def project(p, base):
    """Keep both directional viscous coefficients positive (for the refit)."""
    lim = 0.98 * base["B"]
    return {**p, "dB": max(-lim, min(lim, p["dB"]))}
