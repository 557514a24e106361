"""``deadzone`` -- the drive ignores small commands.

Model: ``u -> sign(u) * max(|u| - width, 0)``, ``width`` [command units] > 0
(half-width of the dead band). Exact under zero-order hold. Unlike Coulomb
friction it follows the sign of the command, not of the motion, so braking
phases (command against velocity) tell them apart.
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
    name="deadzone",
    summary="dead band of the command",
    params=(
        ParamSpec(
            "width",
            "deadzone",
            "command units",
            "half-width of the dead band",
            0.0,
            open_lower=True,
            default=None,
        ),
    ),
    signature="the best linear approximation gains gain as the amplitude grows and the residual "
    "steps with the sign of the command rather than of the velocity (braking phases)",
    fit="equation error against the dead-banded command over a grid of widths, then simulation error",
)


def deadband(u: np.ndarray, width: float) -> np.ndarray:
    return np.sign(u) * np.maximum(np.abs(u) - width, 0.0)


def contribute(p, plant, terms: Terms) -> None:
    w = float(p["width"])
    terms.inputs.append((30, lambda u: deadband(u, w)))


def screen(ctx: ScreenInput) -> Screening:
    _, sse0 = base_fit(ctx)
    mag = np.abs(ctx.cat("u"))
    med = float(np.median(mag[mag > 0])) if np.any(mag > 0) else 1.0
    best = None
    for w in med * np.linspace(0.01, 0.9, 60):
        coef, sse = input_fit(ctx, lambda u, w=w: deadband(u, w))
        if best is None or sse < best[0]:
            best = (sse, w, coef)
    sse, w, coef = best
    evidence = (
        f"the command acts only beyond a dead band (the force residual steps with "
        f"the sign of u, not of v; equation error {100 * (1 - sse / sse0):.0f}% lower)"
    )
    base = {"M": coef[0], "B": coef[1], "coulomb_pos": coef[2], "coulomb_neg": coef[3]}
    n = int(ctx.moving.sum())
    bounds = {"width": (0.0, float(mag.max()) if mag.size else 1.0)}
    return Screening(explained(sse0, sse, 1, n), {"width": float(w)}, bounds, evidence, base=base)
