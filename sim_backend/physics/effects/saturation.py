"""``saturation`` -- the drive limits the command it applies.

Model: ``u -> clip(u, -limit, limit)``, ``limit`` [command units] > 0. Exact
under zero-order hold. With a binary command of one amplitude a limit only
rescales the model; it shows when the command has several levels (two runs of
different amplitude, a multisine).
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
    name="saturation",
    summary="command limit",
    params=(
        ParamSpec(
            "limit",
            "sat",
            "command units",
            "largest |u| applied",
            0.0,
            open_lower=True,
            default=None,
        ),
    ),
    signature="the best linear approximation loses gain as the amplitude grows (run 2 against "
    "run 1) and the residual opposes the command where |u| is largest",
    fit="equation error against the clipped command over a grid of limits (quantiles of |u|), "
    "then simulation error",
)


def contribute(p, plant, terms: Terms) -> None:
    lim = float(p["limit"])
    terms.inputs.append((20, lambda u: np.clip(u, -lim, lim)))


def screen(ctx: ScreenInput) -> Screening:
    _, sse0 = base_fit(ctx)
    mag = np.abs(ctx.cat("u"))
    top = float(mag.max()) if mag.size else 1.0
    best = None
    for lim in np.unique(np.quantile(mag[mag > 0], np.linspace(0.2, 0.995, 60))):
        coef, sse = input_fit(ctx, lambda u, lim=lim: np.clip(u, -lim, lim))
        if best is None or sse < best[0]:
            best = (sse, lim, coef)
    sse, lim, coef = best
    share = float(np.mean(mag > lim))
    evidence = (
        f"the applied command looks clipped at its largest values ({100 * share:.0f}% of "
        f"samples beyond the limit; equation error {100 * (1 - sse / sse0):.0f}% lower)"
    )
    base = {"M": coef[0], "B": coef[1], "coulomb_pos": coef[2], "coulomb_neg": coef[3]}
    n = int(ctx.moving.sum())
    bounds = {"limit": (0.05 * top, 2.0 * top)}
    return Screening(explained(sse0, sse, 1, n), {"limit": float(lim)}, bounds, evidence, base=base)
