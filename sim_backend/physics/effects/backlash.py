"""``backlash`` -- play between the motor and the load.

Model: the motor (inertia ``(1 - ratio) M``, all Coulomb friction) drives the
load (inertia ``ratio M``) through a play of total width ``gap`` [units];
the viscous term splits with the inertia. Engaged, both move as one body;
the play opens when the contact force would pull, the motor crosses it alone
and closing it is an inelastic impact. The sensor sits on the motor, so the
base model sees a lighter axis after each reversal and a velocity drop at
each impact. Sub-stepped.
"""

from __future__ import annotations

import numpy as np

from servobench.errors import UsageError
from servobench.sim_backend.physics.effects.spec import (
    Coupling,
    EffectSpec,
    ParamSpec,
    Screening,
    ScreenInput,
    Terms,
    base_columns,
    base_fit,
    base_values,
    explained,
    regress,
    target,
)

EFFECT = EffectSpec(
    name="backlash",
    summary="play between motor and load",
    params=(
        ParamSpec("gap", "backlash", "units", "total play", 0.0, open_lower=True, default=None),
        ParamSpec(
            "ratio",
            "backlash_ratio",
            "1",
            "share of the inertia behind the play",
            0.02,
            0.95,
            default=0.5,
        ),
    ),
    signature="after each reversal the axis accelerates as if lighter until it has travelled "
    "the play, then its velocity drops at the impact: the residual concentrates right after "
    "reversals and the apparent inertia depends on the engagement state",
    fit="equation error with the inertia switched by a play operator on the measured position "
    "over a grid of gaps, then simulation error on gap and ratio",
)


def contribute(p, plant, terms: Terms) -> None:
    if terms.coupling is not None:
        raise UsageError("backlash cannot be combined with another coupling (resonance)")
    terms.coupling = Coupling("gap", float(p["ratio"]), gap=float(p["gap"]), measured="motor")


def engaged(x: np.ndarray, gap: float) -> np.ndarray:
    """Whether a load behind a play of ``gap`` is being driven (play operator on ``x``,
    compiled: :func:`~servobench.sim_backend.physics.kernels.play_engaged`)."""
    from servobench.sim_backend.physics.kernels import play_engaged

    return play_engaged(np.ascontiguousarray(x, dtype=float), float(gap))


#: Restarts along the steady state's line where the command holds one level each way (a square
#: wave): the current base's Coulomb levels times each of these, its viscous coefficient raised
#: to keep the steady speed ...
STEADY_SHARES = (0.2, 0.4, 0.6)
#: ... where this share of the samples lie within :data:`ONE_LEVEL` of the command's largest
#: magnitude ...
ONE_LEVEL_SHARE = 0.95
#: ... a band relative to that magnitude.
ONE_LEVEL = 0.02


def _steady_line(
    ctx: ScreenInput, guess: dict[str, float]
) -> tuple[tuple[dict[str, float], dict[str, float]], ...]:
    """Starts for a command of one level each way: there the steady state fixes only
    ``coulomb + B v_ss``, a base fitted with the play left out splits it wrongly (its Coulomb
    level five times the true one, B half), and the play's refit stalls on the way along that
    line. Each start moves the base along it, with the screening's guess of the play."""
    u = np.abs(ctx.cat("u"))
    top = float(np.max(u)) if u.size else 0.0
    if not (top > 0 and np.mean(u >= (1.0 - ONE_LEVEL) * top) >= ONE_LEVEL_SHARE):
        return ()
    base = base_values(ctx)
    coulomb = 0.5 * (base["coulomb_pos"] + base["coulomb_neg"])
    if not (base["B"] > 0 and 0 < coulomb < top):
        return ()
    v_ss = (top - coulomb) / base["B"]
    return tuple(
        (
            {
                **base,
                "B": (top - share * coulomb) / v_ss,
                "coulomb_pos": share * base["coulomb_pos"],
                "coulomb_neg": share * base["coulomb_neg"],
            },
            dict(guess),
        )
        for share in STEADY_SHARES
    )


def screen(ctx: ScreenInput) -> Screening:
    m = ctx.moving
    y = target(ctx)
    cols = base_columns(ctx)
    coef0, sse0 = base_fit(ctx)
    a = ctx.cat("a_f")[m]
    x_all = [r.x for r in ctx.runs]
    span = float(max(np.ptp(x) for x in x_all))
    # the smallest gap tried: the median step (0 where the position is quantised coarser than a
    # sample's travel, so most steps are nil), never below a millionth of the travel
    step = max(float(np.median(np.abs(np.concatenate([np.diff(x) for x in x_all])))), 1e-6 * span)
    best = None
    for gap in np.geomspace(step, 0.2 * span, 30):
        eng = np.concatenate([engaged(x, gap) for x in x_all])[m]
        coef, sse = regress([*cols, a * eng], y)
        if coef[0] > 0 and coef[4] > 0 and (best is None or sse < best[0]):
            best = (sse, gap, coef)
    bounds = {"gap": (0.0, 0.5 * span), "ratio": (0.05, 0.9)}
    if best is None:
        best = (sse0, step, np.array([*coef0, 0.0]))
    sse, gap, coef = best
    ratio = float(np.clip(coef[4] / (coef[0] + coef[4]), 0.1, 0.8))
    evidence = (
        f"the apparent inertia drops after each reversal until the axis has crossed a play "
        f"(equation error {100 * (1 - sse / sse0):.0f}% lower)"
    )
    base = {"M": coef[0] + coef[4], "B": coef[1], "coulomb_pos": coef[2], "coulomb_neg": coef[3]}
    guess = {"gap": gap, "ratio": ratio}
    score = explained(sse0, sse, 2, y.size)
    # The load coasts while the play is open, which the play operator ignores: let a quick
    # simulation judge a spread of gaps too.
    others = tuple(
        {"gap": float(g), "ratio": r}
        for g in np.geomspace(2 * step, 0.1 * span, 8)
        for r in (0.3, 0.5)
    )
    return Screening(
        score,
        guess,
        bounds,
        evidence,
        base=base,
        scan=("gap", "ratio"),
        alternatives=others,
        restarts=_steady_line(ctx, guess),
    )
