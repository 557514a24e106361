"""``time_delay`` -- a transport delay of the command (bus, amplifier, computation).

Model: the plant receives ``u(t - delay)``; ``delay`` [s] >= 0. Whole samples
shift the command; the fraction splits each interval at the delay boundary,
so the model stays exact under zero-order hold.
"""

from __future__ import annotations

import numpy as np

from servobench.sim_backend.physics.effects.spec import (
    EffectSpec,
    ParamSpec,
    Screening,
    ScreenInput,
    Terms,
    base_fit,
    explained,
    input_fit,
)

EFFECT = EffectSpec(
    name="time_delay",
    summary="transport delay of the command",
    params=(ParamSpec("delay", "delay", "s", "command delay", 0.0, 1.0, default=None),),
    signature="the residual is correlated with the input at positive lags and the residual "
    "leads the response at every reversal: the measured response starts late",
    fit="equation error against the delayed command over a grid of delays (quarter samples), "
    "then simulation error (the fractional delay keeps the output smooth in the delay)",
)

#: Longest delay searched [samples].
MAX_DELAY_SAMPLES = 12


def contribute(p, plant, terms: Terms) -> None:
    terms.delay_s += float(p["delay"])


def delayed(u: np.ndarray, d: float) -> np.ndarray:
    """Mean command over each interval when ``u`` (ZOH) is delayed by ``d`` samples."""
    m = int(np.floor(d))
    f = d - m
    pad = np.concatenate([np.zeros(m + 1), u])
    cur = pad[1 : 1 + u.size]
    prev = pad[: u.size]
    return f * prev + (1 - f) * cur


def screen(ctx: ScreenInput) -> Screening:
    _, sse0 = base_fit(ctx)
    best = None
    for d in np.arange(0.25, MAX_DELAY_SAMPLES + 0.01, 0.25):
        coef, sse = input_fit(ctx, lambda u, d=d: delayed(u, d))
        if best is None or sse < best[0]:
            best = (sse, d, coef)
    sse, d, coef = best
    dt = ctx.dt_s
    evidence = (
        f"the response lags the command "
        f"(equation error {100 * (1 - sse / sse0):.0f}% lower with the delayed command)"
    )
    base = {"M": coef[0], "B": coef[1], "coulomb_pos": coef[2], "coulomb_neg": coef[3]}
    bounds = {"delay": (0.0, (MAX_DELAY_SAMPLES + 2) * dt)}
    n = int(ctx.moving.sum())
    return Screening(explained(sse0, sse, 1, n), {"delay": d * dt}, bounds, evidence, base=base)
