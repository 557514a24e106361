"""``quantization`` -- the command is applied in steps (DAC or current-loop resolution).

Model: ``u -> step * round(u / step)``, ``step`` [command units] > 0. Exact
under zero-order hold. The simulation output is piecewise constant in
``step``, so the refit searches it on a grid instead of by gradient.
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
    name="quantization",
    summary="command quantized in steps",
    params=(
        ParamSpec(
            "step",
            "quant",
            "command units",
            "quantization step of u",
            0.0,
            open_lower=True,
            default=None,
        ),
    ),
    signature="the residual is correlated with the rounding error step*round(u/step) - u "
    "of the command for one step size, and only where the command takes non-binary values",
    fit="equation error against the rounded command over a fine grid of steps; the refit keeps "
    "the step on that grid (the error is piecewise constant in it)",
)


#: Steps beyond the best the screening offers the quick simulation, each at least :data:`APART`
#: (relative) from the best and from one another.
ALTERNATIVES = 4
APART = 0.1


def quantize(u: np.ndarray, step: float) -> np.ndarray:
    return step * np.round(u / step)


def contribute(p, plant, terms: Terms) -> None:
    q = float(p["step"])
    terms.inputs.append((10, lambda u: quantize(u, q)))


def screen(ctx: ScreenInput) -> Screening:
    _, sse0 = base_fit(ctx)
    top = float(np.max(np.abs(ctx.cat("u")))) or 1.0

    def best_of(steps):
        fits = [(*input_fit(ctx, lambda u, q=q: quantize(u, q))[::-1], q) for q in steps]
        return sorted(fits, key=lambda f: f[0])

    # Coarse, then fine around the best few apart from one another: the error is jagged in the
    # step, and a simulation in closed loop moves a few per cent away from the true step.
    coarse = best_of(top * np.geomspace(0.01, 0.6, 100))
    centres: list[float] = []
    for _, _, step in coarse:
        if all(abs(step / c - 1.0) > APART for c in centres):
            centres.append(float(step))
        if len(centres) == 1 + ALTERNATIVES:
            break
    refined = [min(best_of(c * np.linspace(0.985, 1.015, 15)) + [f for f in coarse if f[2] == c],
                   key=lambda f: f[0]) for c in centres]  # fmt: skip
    sse, coef, q = min(refined, key=lambda f: f[0])
    # The equation error differentiates a noisy velocity and ranks steps loosely: the best of
    # each other neighbourhood goes to the quick simulation as well.
    others = [float(f[2]) for f in refined if f[2] != q]
    evidence = (
        f"the force residual follows the rounding error of the command in steps "
        f"(equation error {100 * (1 - sse / sse0):.0f}% lower)"
    )
    base = {"M": coef[0], "B": coef[1], "coulomb_pos": coef[2], "coulomb_neg": coef[3]}
    n = int(ctx.moving.sum())
    bounds = {"step": (0.5 * q, 2.0 * q)}
    return Screening(
        explained(sse0, sse, 1, n), {"step": float(q)}, bounds, evidence, fixed=("step",), base=base,
        alternatives=tuple({"step": other} for other in others),
    )
